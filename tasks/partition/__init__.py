"""The partition stage."""
