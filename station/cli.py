"""`station` command line (wired by the station issue)."""

from __future__ import annotations

import sys


def main(argv: list[str] | None = None) -> int:
    print("station: not yet implemented (see the station issue); `make demo` runs the estimation demo",
          file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
