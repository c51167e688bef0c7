"""The object store: one interface over a local folder and ``s3://``, conditional writes, the run lease, commits.
"""
