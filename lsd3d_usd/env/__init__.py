"""lsd3d_usd.env"""
