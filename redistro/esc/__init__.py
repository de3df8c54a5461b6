"""The Execution-Stage Controller: one node per robot (manager + workers)."""
