import sys

from usplat_dr.cli import main

sys.exit(main())
