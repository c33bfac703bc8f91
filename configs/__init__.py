"""YAML overrides of the config dataclasses in common.config (default, paper, tiny).

cluster.yaml is not a run config but a Ray cluster-launcher file (``ray up configs/cluster.yaml``).
"""
