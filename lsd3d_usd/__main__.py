from lsd3d_usd.cli import run

run()
