"""lsd3d_usd.actors"""
