"""lsd3d_usd.render"""
