"""Campaigns: a firmware test matrix run on a local pool or a Dask cluster (docs/campaigns.md)."""
