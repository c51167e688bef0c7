"""ms3d.storage"""
