"""Generic engine for content-addressed, resumable pipeline steps. Imports nothing model-specific."""
