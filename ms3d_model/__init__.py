"""ms3d.ms3d_model"""
