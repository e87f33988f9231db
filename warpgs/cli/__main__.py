"""`python -m warpgs.cli train|render|eval ...`."""
import sys

from warpgs.cli.commands import main

sys.exit(main())
