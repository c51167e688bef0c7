"""The repair stage."""
