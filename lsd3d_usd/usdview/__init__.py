"""lsd3d_usd.usdview"""
