"""The work dir: its layout and campus.json, the run manifest, housekeeping, ground-truth and user labels.
"""
