"""Builders of the saved artifacts."""
