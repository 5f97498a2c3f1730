"""`nao-bridge` command line (wired by the bridge issue)."""

from __future__ import annotations

import sys
from typing import List, Optional


def main(argv: Optional[List[str]] = None) -> int:
    print("nao-bridge: not yet implemented (see the bridge issue)", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
