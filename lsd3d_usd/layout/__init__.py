"""lsd3d_usd.layout"""
