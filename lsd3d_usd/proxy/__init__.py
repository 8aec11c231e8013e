"""lsd3d_usd.proxy"""
