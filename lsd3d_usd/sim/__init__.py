"""lsd3d_usd.sim"""
