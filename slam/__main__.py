import sys

from swarmsplat.slam.cli import main

sys.exit(main())
