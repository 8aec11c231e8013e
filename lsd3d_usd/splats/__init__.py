"""lsd3d_usd.splats"""
