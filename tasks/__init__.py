"""ms3d.tasks"""
