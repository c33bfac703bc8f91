"""YAML overrides of the config dataclasses in common.config (default, paper, cluster, tiny)."""
