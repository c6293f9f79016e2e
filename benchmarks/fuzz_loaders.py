"""Fuzz every file loader with mutants of a good file: how many load, are refused, and escape (issue 29).

Runs the sweep of tests/test_fuzz.py (its good files, its mutations, its check) at a larger count: per format, the
mutants that loaded, that were refused with an EfficientTrackError naming the file, and that escaped as any other
exception (a bug: the command line would show a traceback). Each escape is listed with its index, how the mutant was
made and the last line of its traceback; ``--show`` prints the whole traceback of the first few.

    .venv/bin/python benchmarks/fuzz_loaders.py [--mutants 3000] [--seed 29] [--formats "episode .npz,model .pt"]
"""

from __future__ import annotations

import argparse
import shlex
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the sweep lives with its test

from test_fuzz import FORMATS, SEED, sweep  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mutants", type=int, default=3000, help="mutants per format")
    parser.add_argument("--seed", type=int, default=SEED, help="the sweep's seed (the test uses %(default)s)")
    names = [fmt.name for fmt in FORMATS]
    parser.add_argument("--formats", default=",".join(names), help=f"comma-separated formats, of: {', '.join(names)}")
    parser.add_argument("--show", type=int, default=1, help="print the whole traceback of this many escapes per format")
    args = parser.parse_args()
    chosen = [name.strip() for name in args.formats.split(",") if name.strip()]
    unknown = [name for name in chosen if name not in names]
    if unknown:
        parser.error(f"--formats: unknown {', '.join(unknown)}; known: {', '.join(names)}")
    if args.mutants < 1:
        parser.error("--mutants must be at least 1")
    print(f"{args.mutants} mutants per format, seed {args.seed}")
    print(f"{'format':24s} {'loaded':>8s} {'refused':>8s} {'escaped':>8s} {'ms/mutant':>10s}")
    total_escaped = 0
    with tempfile.TemporaryDirectory() as tmp:
        for fmt in (fmt for fmt in FORMATS if fmt.name in chosen):
            outcome = sweep(fmt, Path(tmp) / fmt.name.replace(" ", "_"), args.mutants, args.seed)
            per = outcome.seconds / args.mutants * 1000
            escaped = outcome.escaped
            total_escaped += len(escaped)
            print(f"{fmt.name:24s} {outcome.loaded:8d} {outcome.refused:8d} {len(escaped):8d} {per:10.2f}", flush=True)
            for i, (index, what, text) in enumerate(escaped):
                last = text.strip().splitlines()[-1] if text.strip() else "?"
                print(f"    escaped: mutant {index} ({what[:120]}): {last[:200]}")
                if i < args.show:
                    print("      " + text.strip().replace("\n", "\n      "))
    print(f"escaped in all: {total_escaped}")
    print("command: python " + " ".join(shlex.quote(a) for a in sys.argv))


if __name__ == "__main__":
    main()
