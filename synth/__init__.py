"""ms3d.synth"""
