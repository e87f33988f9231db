import sys

from warpgs.viewer.cli import main

sys.exit(main())
