"""The finished rows of several `mono-hdr bench curves` runs in one plot (a row of panels per scene,
a line per row), for runs kept in separate folders, such as the image sizes' (benchmarks/run_sizes.sh):

    python benchmarks/plot_curves.py benchmarks/results/sizes/curves_256.png \\
        benchmarks/results/sizes/gs256 benchmarks/results/sizes/gs256_full benchmarks/results/sizes/nerf256
"""

import json
from pathlib import Path

from mono_hdr_plugin.apps.bench import script_args as args_of
from mono_hdr_plugin.apps.bench.curves import plot_curves


def finished_rows(folders: list[Path]) -> list[dict]:
    """The rows of FOLDER/curves.json that finished, over all folders, in their order."""
    rows = []
    for folder in folders:
        path = folder / "curves.json"
        if not path.is_file():
            raise SystemExit(f"{path} does not exist: run `mono-hdr bench curves --out {folder}` first")
        rows += [row for row in json.loads(path.read_text())["rows"].values() if row["status"] == "ok"]
    return rows


def main() -> None:
    parser = args_of.script_parser(__doc__)
    parser.add_argument("png", type=Path, help="the plot to write")
    parser.add_argument("folders", type=Path, nargs="+", help="output folders of `mono-hdr bench curves`")
    args = parser.parse_args()
    rows = finished_rows(args.folders)
    if not rows:
        raise SystemExit(f"no finished row in {' '.join(map(str, args.folders))}")
    plot_curves(rows, args.png)
    print(f"{len(rows)} rows plotted in {args.png}")


if __name__ == "__main__":
    main()
