"""Zarr-backed replay shards, the sharded client/sampler and the `python -m replay` inspector."""
