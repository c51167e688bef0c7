"""ms3d.flows"""
