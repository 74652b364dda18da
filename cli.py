"""The `splatwright` command line: one sub-command per verb, each a pair of functions.

To add a verb, write `_add_<verb>(parser)` and `_run_<verb>(args)` and list them in VERBS.
"""

import argparse
import json
import sys
import time

import numpy as np


class Progress:
    """A one-line progress indicator on stderr: `progress(done, total, label)`."""

    def __init__(self, stream=sys.stderr, min_interval=0.1):
        self.stream, self.min_interval, self._last = stream, min_interval, 0.0

    def __call__(self, done, total, label=""):
        now = time.monotonic()
        if done < total and now - self._last < self.min_interval:
            return
        self._last = now
        pct = 100.0 * done / total if total else 100.0
        end = "\n" if done >= total else "\r"
        self.stream.write(f"{label} {pct:5.1f}% ({done}/{total}){end}")
        self.stream.flush()


def _parse_vec(text):
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got '{text}'") from None
    return np.array(values)


# info ---------------------------------------------------------------------------------------------

def _add_info(p):
    p.add_argument("file", help="a splat file (.ply, .usd/.usda/.usdc/.usdz, .spz, .splat)")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def summarize(cloud):
    """The statistics `info` prints, as plain Python values."""
    finite = cloud.finite_mask()
    pos = cloud.positions[finite]
    stats = lambda a: {"min": float(a.min()), "median": float(np.median(a)), "max": float(a.max())} \
        if len(a) else None
    return {
        "count": len(cloud),
        "sh_degree": cloud.sh_degree,
        "bbox_min": pos.min(axis=0).tolist() if len(pos) else None,
        "bbox_max": pos.max(axis=0).tolist() if len(pos) else None,
        "opacity": stats(cloud.opacities[finite]),
        "scale": stats(cloud.scales[finite].max(axis=1)),
        "non_finite_splats": int((~finite).sum()),
        "problems": cloud.problems(),
        "extras": sorted(cloud.extras),
    }


def _run_info(args):
    from .io import format_of, read_splats
    cloud = read_splats(args.file)
    summary = {"file": args.file, "format": format_of(args.file), **summarize(cloud)}
    if args.json:
        print(json.dumps(summary))
    else:
        for key, value in summary.items():
            print(f"{key:>18}: {value}")
    return 0


# convert ------------------------------------------------------------------------------------------

def _add_convert(p):
    p.add_argument("input")
    p.add_argument("output")
    p.add_argument("--sh-degree", type=int, choices=range(4), help="truncate SH to this degree")


def _run_convert(args):
    from .io import read_splats, write_splats
    cloud = read_splats(args.input)
    if args.sh_degree is not None:
        cloud = cloud.with_sh_degree(args.sh_degree)
    write_splats(args.output, cloud)
    print(f"wrote {len(cloud)} splats (SH degree {cloud.sh_degree}) to {args.output}")
    return 0


# demo (the main job) ------------------------------------------------------------------------------

def _add_demo(p):
    p.add_argument("--out", default="out/demo", help="folder for everything the demo writes")


def _run_demo(args):
    from .demo import run_demo
    return run_demo(args.out, progress=Progress())


VERBS = {
    "info": (_add_info, _run_info, "summarise a splat file"),
    "convert": (_add_convert, _run_convert, "convert between splat formats"),
    "demo": (_add_demo, _run_demo, "run the built-in demo scene end to end"),
}


def build_parser():
    parser = argparse.ArgumentParser(prog="splatwright", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="verb", required=True)
    for name, (add, run, help_text) in VERBS.items():
        p = sub.add_parser(name, help=help_text)
        add(p)
        p.set_defaults(run=run)
    return parser


def main(argv=None):
    args = build_parser().parse_args(argv)
    from .core import SplatValidationError
    from .io import SplatFileError
    try:
        return args.run(args)
    except (SplatFileError, SplatValidationError) as exc:
        print(f"splatwright {args.verb}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
