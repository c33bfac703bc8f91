"""Config, geometry, TSDF, gripper specs and encodings, object sets, network and policy."""
