"""Input files by identity and location: a local path or a URL, stable source ids, content fingerprints.
"""
