"""lsd3d_usd.ggds"""
