"""Simulation (scenes, cameras, gripper execution), the GraspActor and evaluation runs."""
