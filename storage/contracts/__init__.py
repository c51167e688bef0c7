"""The stage-to-stage contracts: staging runs, surface samples, the region plan, region and tile meshes.
"""
