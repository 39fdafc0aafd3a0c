"""Readers and writers for the contract's files (YAML, tracks CSV, TUM, velocity CSV)."""
