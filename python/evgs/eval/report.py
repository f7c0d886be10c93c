"""Per-run report: ``report.md`` and a self-contained ``report.html`` (figures embedded as base64), both
rendered from one list of blocks so the two never disagree."""

from __future__ import annotations

import base64
import html
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evgs.eval.run import RunEvaluation
from evgs.eval.trajectory import rmse_or_nan
from evgs.io_util import atomic_path


@dataclass(frozen=True)
class Table:
    header: list[str]
    rows: list[list[str]]


@dataclass(frozen=True)
class Figure:
    caption: str
    path: Path


Block = tuple[str, str] | Table | Figure  # ("h2" | "p" | "li", text)


def fmt_length(x: float) -> str:
    """A length in ground-truth units (metres): centimetres below 1 m, as in the paper's tables."""
    if not np.isfinite(x):
        return "/"
    return f"{x * 100:.2f} cm" if abs(x) < 1.0 else f"{x:.3f} m"


def fmt_num(x: float | None, spec: str, unit: str = "") -> str:
    return "/" if x is None or not np.isfinite(x) else f"{x:{spec}}{unit}"


def build_blocks(ev: RunEvaluation, figures: dict[str, Path]) -> list[Block]:
    tr = ev.traj
    img = ev.images.summary() if ev.images is not None else {}
    main_header = ["Sequence", "Frames", "RMSE", "Drift", "PSNR", "LPIPS"]
    main_row = [
        ev.sequence.name,
        ev.frame_range,
        fmt_length(tr.ate_rmse),
        fmt_num(tr.drift_deg, ".1f", "°"),
        fmt_num(img.get("psnr_db"), ".2f", " dB"),
        fmt_num(img.get("lpips"), ".2f"),
    ]
    if ev.elope_score is not None:
        main_header.append("Score")
        main_row.append(fmt_num(ev.elope_score, ".4f"))
    summ = tr.summary()
    blocks: list[Block] = [
        ("h1", f"Evaluation — {ev.label}"),
        ("p", f"Sequence: {ev.sequence.name} ({ev.sequence.root}); run directory: {ev.run_dir}."),
        ("h2", "Pose estimation & reconstruction metrics"),
        Table(main_header, [main_row]),
        ("h2", "Translation metrics (Umeyama Sim(3) alignment)"),
        Table(
            ["Axis", "RMSE"],
            [[a, fmt_length(v)] for a, v in zip("XYZ", tr.axis_rmse, strict=True)]
            + [["Total", fmt_length(tr.ate_rmse)]],
        ),
        ("h2", "Orientation metrics (first-pose alignment; the gaze under the Sim(3))"),
        Table(
            ["Axis", "RMSE"],
            [[a, f"{v:.3f}°"] for a, v in zip(("Yaw", "Pitch", "Roll"), tr.ypr_rmse_deg, strict=True)]
            + [["Angle (eq. 17)", f"{summ['rot_err_rmse_deg']:.3f}°"]]
            + [["Drift @ end", f"{tr.drift_deg:.3f}°"]]
            + [["Gaze (under the Sim(3))", fmt_num(summ["gaze_err_rmse_deg"], ".3f", "°")]],
        ),
        ("h2", "Relative pose error (Sim(3)-aligned)"),
        Table(
            ["Pairs", "Count", "Translation RMSE", "Rotation RMSE"],
            [
                [
                    f"every {r.delta:g} {r.unit}",
                    str(len(r.pairs)),
                    fmt_length(rmse_or_nan(r.trans)),
                    fmt_num(rmse_or_nan(r.rot_deg), ".3f", "°"),
                ]
                for r in (tr.rpe_frame, tr.rpe_metre)
            ],  # fmt: skip
        ),
    ]
    if ev.images is not None:
        blocks += [
            ("h2", "Image metrics"),
            Table(
                ["PSNR", "SSIM", "LPIPS", "Frames"],
                [
                    [
                        f"{img['psnr_db']:.2f} dB",
                        f"{img['ssim']:.4f}",
                        f"{img['lpips']:.4f}",
                        str(len(ev.images.psnr)),
                    ]
                ],
            ),
        ]
    if ev.depth is not None:
        d = ev.depth.summary()
        blocks += [
            ("h2", "Map depth against the simulated scene (ground-truth viewpoints)"),
            Table(
                ["Depth L1", "Relative error", "Coverage", "Spill", "Frames"],
                [
                    [
                        fmt_num(d["depth_l1_m"], ".3f", " m"),
                        fmt_num(d["depth_err_pct"], "+.1f", " %"),
                        f"{d['depth_coverage']:.0%}",
                        fmt_num(d["depth_spill"], ".0%"),
                        str(len(ev.depth.frames)),
                    ]
                ],
            ),
        ]
    blocks.append(("h2", "Figures"))
    captions = {
        "trajectory": "Trajectory: estimate (Sim(3)-aligned) vs ground truth",
        "translation": "Translation evolution",
        "rpy": "Roll, pitch, yaw evolution",
        "orientation_error": f"Orientation error evolution — drift @ end frame: {tr.drift_deg:.3f}°",
        "velocity": "Velocity" + (f" — score: {ev.elope_score:.4f}" if ev.elope_score is not None else ""),
        "depth_error": "Map depth against the scene per frame (< 0: nearer the camera), and its coverage",
        "depth_views": "Scene depth, map depth and their relative error at the first, middle and last frames",
    }
    blocks += [Figure(captions.get(k, k), p) for k, p in figures.items()]
    blocks += [("h2", "Settings"), ("pre", _settings_text(ev))]
    blocks += [("h2", "Diagnostics")] + _diagnostics(ev)
    return blocks


def _settings_text(ev: RunEvaluation) -> str:
    """The run's resolved configuration, verbatim."""
    return (ev.run_dir / "config.toml").read_text().strip()


def _diagnostics(ev: RunEvaluation) -> list[Block]:
    tr = ev.traj
    items = [
        f"associated poses: {len(ev.assoc.t)} (ground truth interpolated at the estimate's timestamps); "
        f"dropped: {ev.assoc.dropped}",
        f"Sim(3) scale (estimate → ground truth): {tr.sim3.s:.6g}",
        "SSIM: Gaussian window σ = 1.5, 11×11; LPIPS: AlexNet, v0.1 linear heads; PSNR peak 1.0",
    ]
    items += ev.notes
    diag = ev.run_dir / "diagnostics"
    if diag.is_dir():
        items += [f"diagnostics file: diagnostics/{p.name}" for p in sorted(diag.iterdir())]
    blocks: list[Block] = [("li", s) for s in items]
    scalars = _pipeline_scalars(ev.run_dir / "metrics.json")
    if scalars:
        blocks += [("p", "Pipeline metrics (metrics.json):"), Table(["Key", "Value"], scalars)]
    return blocks


def _pipeline_scalars(path: Path) -> list[list[str]]:
    """Top-level numbers and strings of the pipeline's own metrics.json (nested data is left out)."""
    if not path.is_file():
        return []
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        return [["(unreadable)", f"{path.name}: line {e.lineno}: {e.msg}"]]
    if not isinstance(doc, dict):
        return []
    return [[k, f"{v:.6g}" if isinstance(v, float) else str(v)] for k, v in doc.items()
            if isinstance(v, (int, float, str, bool))]  # fmt: skip


def to_markdown(blocks: list[Block], base: Path) -> str:
    out: list[str] = []
    for b in blocks:
        if isinstance(b, Table):
            out += ["| " + " | ".join(b.header) + " |", "|" + "---|" * len(b.header)]
            out += ["| " + " | ".join(r) + " |" for r in b.rows]
            out.append("")
        elif isinstance(b, Figure):
            out += [f"![{b.caption}]({b.path.relative_to(base).as_posix()})", f"*{b.caption}*", ""]
        else:
            kind, text = b
            if kind == "h1":
                out += [f"# {text}", ""]
            elif kind == "h2":
                out += [f"## {text}", ""]
            elif kind == "li":
                out.append(f"- {text}")
            elif kind == "pre":
                out += ["```toml", text, "```", ""]
            else:
                out += [text, ""]
    return "\n".join(out) + "\n"


_CSS = (
    "body{font-family:sans-serif;max-width:60em;margin:2em auto;padding:0 1em}"
    "table{border-collapse:collapse;margin:.5em 0 1.5em}td,th{border:1px solid #bbb;padding:.3em .8em}"
    "th{background:#eee}figure{margin:1em 0}img{max-width:100%}"
    "pre{background:#f6f6f6;padding:1em;overflow:auto}"
)


def to_html(blocks: list[Block], title: str) -> str:
    """A single HTML file: inline CSS, images as data URIs, no external references."""
    e = html.escape
    out = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{e(title)}</title>",
           f"<style>{_CSS}</style></head><body>"]  # fmt: skip
    in_list = False
    for b in blocks:
        is_li = isinstance(b, tuple) and b[0] == "li"
        if in_list and not is_li:
            out.append("</ul>")
        if is_li and not in_list:
            out.append("<ul>")
        in_list = is_li
        if isinstance(b, Table):
            out.append("<table><tr>" + "".join(f"<th>{e(h)}</th>" for h in b.header) + "</tr>")
            out += ["<tr>" + "".join(f"<td>{e(c)}</td>" for c in r) + "</tr>" for r in b.rows]
            out.append("</table>")
        elif isinstance(b, Figure):
            data = base64.b64encode(b.path.read_bytes()).decode("ascii")
            out.append(
                f"<figure><img alt='{e(b.caption)}' src='data:image/png;base64,{data}'>"
                f"<figcaption>{e(b.caption)}</figcaption></figure>"
            )
        else:
            kind, text = b
            tag = {"h1": "h1", "h2": "h2", "li": "li", "pre": "pre"}.get(kind, "p")
            out.append(f"<{tag}>{e(text)}</{tag}>")
    if in_list:
        out.append("</ul>")
    out.append("</body></html>")
    return "\n".join(out) + "\n"


def write_report(ev: RunEvaluation, figures: dict[str, Path], out_dir: Path) -> tuple[Path, Path]:
    """Write ``report.md`` and ``report.html`` into ``out_dir`` (figures are referenced relative to it)."""
    blocks = build_blocks(ev, figures)
    md, page = out_dir / "report.md", out_dir / "report.html"
    with atomic_path(md) as tmp:
        tmp.write_text(to_markdown(blocks, out_dir))
    with atomic_path(page) as tmp:
        tmp.write_text(to_html(blocks, f"evgs eval — {ev.label}"))
    return md, page
