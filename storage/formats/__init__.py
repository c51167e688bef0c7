"""Input and output file formats: one module per format, readers in registries keyed by extension.
"""
