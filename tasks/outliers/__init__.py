"""The outliers stage."""
