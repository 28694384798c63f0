"""docs/fractional.md's accuracy and cost tables and figure, from ``fojax accuracy``.

    python -m experiments.accuracy_report [--out results/fractional] [--update-doc]

Runs ``fojax accuracy --out DIR`` (every fractional method against exact
Riemann-Liouville results, float64, 80 s at 1 ms), then, with ``--update-doc``, puts
its ``accuracy.md`` into the ``accuracy`` block of docs/fractional.md and its figure at
``docs/fractional_accuracy.png``.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

from fojax.cli import accuracy, output

DOC = Path(__file__).resolve().parents[1] / "docs" / "fractional.md"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m experiments.accuracy_report")
    parser.add_argument("--out", type=Path, default=Path("results/fractional"))
    parser.add_argument("--update-doc", action="store_true")
    args = parser.parse_args(argv)
    status = accuracy.main(["--out", str(args.out)])
    if status or not args.update_doc:
        return status
    text = (args.out / "accuracy.md").read_text().strip()
    figure = args.out / "accuracy.png"
    if figure.is_file():
        shutil.copy2(figure, DOC.parent / "fractional_accuracy.png")
        text += "\n\n![worst error against order](fractional_accuracy.png)"
    load = ", ".join(f"{x:g}" for x in output.load_average()) or "unknown"
    output.splice(DOC, f"{text}\n\nLoad average at the end: {load}.", name="accuracy")
    return 0


if __name__ == "__main__":
    sys.exit(main())
