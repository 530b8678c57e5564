"""Shared pytest fixtures for procedural scenes and datasets (filled in by the scenes work)."""
