"""Gripper specs and generators, object-set definitions, fence and mount; found via importlib.resources."""
