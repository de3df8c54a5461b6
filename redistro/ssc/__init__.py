"""The Strategy-Stage Controller: task planning, trajectories, control laws, coordination."""
