"""Deliberately broken plugins: each entry point fails in a different way."""
