"""Run the benchmarks and write docs/benchmarks.md (machine, date, one section per benchmark).

Each module ``tools/benchmarks/bench_<name>.py`` defines ``run() -> str`` returning a Markdown
section (a heading, what was compared, the command, the table). ``--only NAME`` reruns one
section and keeps the others already in the file.
"""

from __future__ import annotations

import argparse
import datetime
import importlib
import os
import pkgutil
import platform
import re
import sys
from pathlib import Path

import tools.benchmarks as benchmarks_pkg

BEGIN = "<!-- bench:{name} -->"
END = "<!-- /bench:{name} -->"


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, {platform.system()} {platform.release()}"


def available() -> list[str]:
    return sorted(m.name[len("bench_"):] for m in pkgutil.iter_modules(benchmarks_pkg.__path__) if m.name.startswith("bench_"))


def section(name: str, body: str) -> str:
    stamp = datetime.date.today().isoformat()
    return f"{BEGIN.format(name=name)}\n{body.rstrip()}\n\n_Run {stamp} on {machine()}._\n{END.format(name=name)}\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="docs/benchmarks.md")
    parser.add_argument("--only", action="append", choices=available(), help="benchmark(s) to rerun")
    args = parser.parse_args(argv)
    out = Path(args.out)
    text = out.read_text() if out.exists() else "# Benchmarks\n\nWritten by `make bench` (`python -m tools.bench`).\n\n"
    for name in args.only or available():
        print(f"bench: {name} ...", file=sys.stderr, flush=True)
        body = importlib.import_module(f"tools.benchmarks.bench_{name}").run()
        new = section(name, body)
        pattern = re.compile(re.escape(BEGIN.format(name=name)) + r".*?" + re.escape(END.format(name=name)) + r"\n", re.S)
        text = pattern.sub(lambda _: new, text) if pattern.search(text) else text.rstrip("\n") + "\n\n" + new
        out.write_text(text)
    print(f"bench: wrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
