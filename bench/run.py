"""Run every benchmark under bench/ and write bench/REPORT.md with PNG plots beside it.

./run bench            all topics, full size
./run bench --quick    smaller inputs, for a smoke test
./run bench render ply only these topics (their sections of an existing report are replaced,
                       the others kept)
./run bench articulation --only blender-float32
                       only these parts of a topic (its PARTS): their rows replace the rows of the
                       same case in the topic's section, the other rows are kept
"""

import argparse
import importlib
import sys
import time
import traceback
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from common import machine  # noqa: E402

NOT_TOPICS = {"common", "run"}


def topics():
    return sorted(p.stem for p in HERE.glob("*.py") if p.stem not in NOT_TOPICS and not p.stem.startswith("_"))


def fmt(v):
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.3g}"
    return str(v)


def table(rows):
    err_keys = sorted({k for r in rows for k in r.error})
    extra_keys = sorted({k for r in rows for k in r.extra})
    head = ["case", "median s", "± s", "baseline s", "speed-up"] + err_keys + extra_keys
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [
            r.case,
            fmt(r.timing.median),
            fmt(r.timing.spread),
            fmt(r.baseline.median) if r.baseline else "",
            f"{r.ratio:.3g}x" if r.ratio else "",
        ]
        cells += [fmt(r.error.get(k)) for k in err_keys] + [fmt(r.extra.get(k)) for k in extra_keys]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(topic, rows, out_dir):
    """Speed against error for a topic's rows that carry both; returns the PNG name or None."""
    err_keys = [
        k
        for k in sorted({k for r in rows for k in r.error})
        if all(isinstance(r.error.get(k), (int, float)) for r in rows if k in r.error)
    ]
    if not err_keys:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    key = err_keys[0]
    pts = [(r.error[key], r.timing.median, r.timing.spread, r.case) for r in rows if key in r.error]
    fig, ax = plt.subplots(figsize=(6, 4))
    for e, t, s, name in pts:
        ax.errorbar([e], [t], yerr=[s], fmt="o", capsize=3)
        # Long labels run off the figure rather than shrink the axes to make room for them.
        ax.annotate(name, (e, t), fontsize=7, xytext=(3, 3), textcoords="offset points").set_in_layout(False)
    ax.set_xlabel(key)
    ax.set_ylabel("median seconds")
    ax.set_title(f"{topic}: speed against {key}")
    if all(t > 0 for _, t, _, _ in pts):
        ax.set_yscale("log")
    fig.tight_layout()
    name = f"{topic}.png"
    fig.savefig(out_dir / name, dpi=110)
    plt.close(fig)
    return name


def _table_rows(markdown):
    """(column names, [{column: cell}]) of the first table in a report section."""
    lines = [line for line in markdown.splitlines() if line.startswith("|")]
    if len(lines) < 2:
        return [], []
    cells = lambda line: [c.strip() for c in line.strip().strip("|").split(" | ")]  # noqa: E731
    head = cells(lines[0])
    return head, [dict(zip(head, cells(line))) for line in lines[2:]]


def merge_rows(old_section, rows):
    """The section `old_section` with `rows` in it: each replaces the row of the same case, or is
    added; columns the old table lacks are added at its end."""
    old_head, old_rows = _table_rows(old_section)
    new_head, new_rows = _table_rows(table(rows))
    head = old_head + [c for c in new_head if c not in old_head]
    fresh = {r["case"]: r for r in new_rows}
    merged = [fresh.pop(r["case"], r) for r in old_rows] + list(fresh.values())
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(r.get(c, "") for c in head) + " |" for r in merged]
    start = old_section.index("|") if "|" in old_section else len(old_section)
    end = old_section.find("\n\n", start)
    end = len(old_section) if end < 0 else end
    return old_section[:start] + "\n".join(lines) + old_section[end:]


def _old_sections(report):
    old = {}
    if report.exists():
        for part in report.read_text().split("\n## ")[1:]:
            old[part.split("\n", 1)[0].strip()] = "## " + part.rstrip() + "\n"
    return old


def _merge_with_existing(report, sections):
    """Keep the existing report's sections for topics not run this time, in topic order."""
    fresh = {sec.split("\n", 1)[0][3:].strip(): sec for sec in sections}
    merged = {**_old_sections(report), **fresh}
    return [merged[t] for t in sorted(merged)]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("topics", nargs="*", help=f"default: all of {', '.join(topics())}")
    parser.add_argument("--quick", action="store_true", help="smaller inputs (smoke test)")
    parser.add_argument("--report", default=str(HERE / "REPORT.md"))
    parser.add_argument(
        "--only",
        action="append",
        metavar="PART",
        help="run only this part of the topic (a key of its PARTS); rows merged into its section",
    )
    args = parser.parse_args(argv)
    from splatwright.core.memory import numpy_huge_pages

    numpy_huge_pages(False)  # as the Blender extension and the command line run (core.memory)
    report = Path(args.report)
    report.parent.mkdir(parents=True, exist_ok=True)
    sections, failed = [], []
    for topic in args.topics or topics():
        print(f"== {topic}", flush=True)
        t0 = time.perf_counter()
        try:
            module = importlib.import_module(topic)
            if args.only:
                rows = [row for part in args.only for row in module.PARTS[part](args.quick)]
            else:
                rows = module.run(quick=args.quick)
        except Exception:
            traceback.print_exc()
            failed.append(topic)
            continue
        old = _old_sections(report).get(topic)
        if args.only and old is not None:
            parts = ", ".join(args.only)
            stamp = f"_{time.perf_counter() - t0:.0f} s for {parts}, measured {time.strftime('%Y-%m-%d %H:%M')}._"
            kept = "\n\n".join(
                p
                for p in merge_rows(old, rows).rstrip().split("\n\n")
                if not (p.startswith("_") and f" s for {parts}, measured" in p)
            )
            sections.append(kept + "\n\n" + stamp + "\n")
            continue
        png = plot(topic, rows, report.parent)
        section = f"## {topic}\n\n{table(rows)}\n"
        if png:
            section += f"\n![{topic}]({png})\n"
        sections.append(
            section + f"\n_{time.perf_counter() - t0:.0f} s for this topic, measured "
            f"{time.strftime('%Y-%m-%d %H:%M')}{' at quick sizes' if args.quick else ''}._\n"
        )
    sections = _merge_with_existing(report, sections)
    header = (
        f"# Benchmark report\n\nMachine: {machine()}. Written by `./run bench`. Every time is the median of "
        "several runs, ± half their range; speed-up is baseline time / our time, both measured in "
        "this run.\n"
    )
    report.write_text(header + "\n" + "\n".join(sections))
    print(f"wrote {report}")
    if failed:
        print(f"failed topics: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
