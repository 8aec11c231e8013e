import sys

from lsd3d_usd.cli import main

sys.exit(main())
