"""The regions stage."""
