"""What every warpgs command line shares: exit codes and the one-line error report."""
from __future__ import annotations

import sys

EXIT_CONFIG, EXIT_NONFINITE, EXIT_DISTRIBUTED, EXIT_INTERRUPTED = 2, 3, 4, 130


def report_error(prog: str, message: str, code: int) -> int:
    """Print `prog: error: message` on stderr and return `code` (the process's exit status)."""
    print(f"{prog}: error: {message}", file=sys.stderr)
    return code
