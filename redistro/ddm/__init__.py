"""Data Distribution Managers: Robot Group Shared Data between nodes."""
