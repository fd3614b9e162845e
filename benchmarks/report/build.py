"""``benchmarks/RESULTS.md`` and the README's results summary, built from the JSON the benchmark
scripts saved: no number in either is typed by hand.

    python -m benchmarks.report            # rewrite RESULTS.md and the README's summary
    python -m benchmarks.report --check    # exit 1, naming each section that differs or is stale

RESULTS.md holds one section per published table, grouped by what it measures; each section names
its source files, when they were measured, on what machine and, where recorded, the command and
commit that rerun them. The README holds only the summary between its markers (the claims table and
the overview figure) and the fine-tuning table between its own, and links to RESULTS.md. Each results
file has a section keyed by its name; a file without one is listed by name, so nothing saved is
silently left out. Quick-mode files (``"quick": true``) are never reported.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from benchmarks.report import finetune_overview
from benchmarks.report.distillation import render_distillation
from benchmarks.report.finetune import (
    render_critic_bias,
    render_finetune_cost,
    render_noise_authorities,
    render_reinflow_cost,
)
from benchmarks.report.speed import (
    render_env_throughput,
    render_export_latency,
    render_image_latency,
    render_image_train,
    render_latency,
    render_latency_cuda,
    render_network_cost,
    render_sampler,
    render_sim_throughput,
    render_train_throughput,
)
from benchmarks.report.staleness import REPO, TRAILER, SectionStatus, section_status
from benchmarks.report.success import (
    render_ablations,
    render_experts,
    render_main_job,
    render_multimodal,
    render_network_success,
    render_open_loop,
    render_pusht_modes,
    render_success,
    render_training_runs,
)
from benchmarks.report.tables import link, source_line

__all__ = [
    "GROUPS",
    "Section",
    "build_finetune_block",
    "build_results",
    "build_summary",
    "code_stale_sections",
    "main",
    "stale_sections",
]

BEGIN, END = "<!-- results:begin (python -m benchmarks.report) -->", "<!-- results:end -->"
#: the README's fine-tuning table (optional: a README without these markers has none)
FT_BEGIN, FT_END = "<!-- finetune:begin (python -m benchmarks.report) -->", "<!-- finetune:end -->"
RESULTS = Path("benchmarks/results")
#: the generated document of every published table
RESULTS_DOC = Path("benchmarks/RESULTS.md")
#: the figure of every success file's curves, which the report draws from them beside its table
OVERVIEW_PLOT = "success_overview.png"


@dataclass(frozen=True)
class Section:
    """One published table: the files whose names match ``pattern``, under ``title``. ``render`` takes
    one file's data (one block per file, each under its source line) or, when ``merged``, the list of
    (name, data) of every matching file (one table, its sources listed under it, numbered).
    ``produced_by``: what code produces its figures (names of
    :data:`~benchmarks.report.staleness.PRODUCERS`), against which its files' commits date it."""

    pattern: str
    title: str
    render: Callable[[Any], str]
    merged: bool = False
    produced_by: tuple[str, ...] = ()


def _arms(files: list[tuple[str, dict]]) -> str:
    return finetune_overview.arms_table([(Path(name), data) for name, data in files])


#: what produces a trained policy's figures (names of ``staleness.PRODUCERS``)
TRAINED = ("training", "evaluation", "the policy")
#: what produces a network's or a sampler's speed
POLICY = ("the policy",)

#: RESULTS.md's groups in order, each a heading and its sections
GROUPS: dict[str, list[Section]] = {
    "Success, convergence and ablations": [
        Section(r"main_job(_mlp)?\.json", "Main job", render_main_job, produced_by=(*TRAINED, "the experts")),
        Section(
            r"success_.*\.json",
            "Success and convergence, every task and method",
            render_success,
            True,
            produced_by=TRAINED,
        ),
        Section(
            r"distillation_.*\.json",
            "Distillation-based fast policies (the paper's second table)",
            render_distillation,
            produced_by=TRAINED,
        ),
        Section(
            r"network_success\.json",
            "State denoisers: success of the MLP against the UNet",
            render_network_success,
            produced_by=TRAINED,
        ),
        Section(
            r"training_.*\.json",
            "Trained policies (default budget, one seed)",
            render_training_runs,
            produced_by=TRAINED,
        ),
        Section(
            r"open_loop_.*\.json",
            "Open-loop action error of the trained runs",
            render_open_loop,
            produced_by=TRAINED,
        ),
        Section(r"ablations_.*\.json", "Ablations", render_ablations, produced_by=TRAINED),
    ],
    "Multi-modality": [
        Section(r"multimodal\.json", "Multi-modality (toy)", render_multimodal, produced_by=TRAINED),
        Section(
            r"pusht_modes\.json",
            "Multi-modality on PushT: which way around the T",
            render_pusht_modes,
            produced_by=(*TRAINED, "the experts"),
        ),
    ],
    "Speed: inference and training": [
        Section(
            r"latency(_mlp|_image|_samplers_cuda|_samplers_cuda_image)?\.json",
            "Per-chunk latency, every sampler",
            render_latency,
            True,
            produced_by=POLICY,
        ),
        Section(
            r"latency_cuda.*\.json",
            "CUDA latency at batch 1: eager, graph, compile",
            render_latency_cuda,
            produced_by=POLICY,
        ),
        Section(
            r"image_latency\.json",
            "Image policy: latency against its floor",
            render_image_latency,
            produced_by=POLICY,
        ),
        Section(
            r"image_train\.json",
            "Image policy: training from the memory-mapped buffer",
            render_image_train,
            produced_by=("training", "the policy"),
        ),
        Section(
            r"train_throughput_.*\.json",
            "Training step against the bare update",
            render_train_throughput,
            produced_by=("training", "the policy"),
        ),
        Section(
            r"export_latency\.json",
            "Deployable policy: exported program and ONNX",
            render_export_latency,
            produced_by=(*POLICY, "export"),
        ),
        Section(
            r"network_cost\.json",
            "State denoisers: the UNet against the MLP",
            render_network_cost,
            produced_by=POLICY,
        ),
    ],
    "Fine-tuning": [
        Section(
            r"finetune_online_.*\.json",
            "Online fine-tuning: every arm",
            _arms,
            True,
            produced_by=(*TRAINED, "fine-tuning"),
        ),
        Section(
            r"finetune_cost_.*\.json",
            "Fine-tuning: cost of an update and of acting",
            render_finetune_cost,
            True,
            produced_by=(*POLICY, "fine-tuning"),
        ),
        Section(
            r"noise_authority.*\.json",
            "Steering authority of the input noise (what DSRL can move)",
            render_noise_authorities,
            True,
            produced_by=(*POLICY, "fine-tuning"),
        ),
        Section(
            r"reinflow_cost_.*\.json",
            "Plan B's cost: PPO over the noisy 2-NFE chain (ReinFlow's route)",
            render_reinflow_cost,
            produced_by=(*POLICY, "fine-tuning"),
        ),
        Section(
            r"critic_bias_.*\.json",
            "Critic bias: Q on the replay data against its Monte-Carlo value",
            render_critic_bias,
            produced_by=(*TRAINED, "fine-tuning"),
        ),
    ],
    "Simulators, experts and data": [
        Section(
            r"env_throughput_.*\.json",
            "Environment throughput",
            render_env_throughput,
            produced_by=("the simulators",),
        ),
        Section(r"sampler\.json", "Replay-buffer sampling", render_sampler, produced_by=("training",)),
        Section(
            r"(pusht|robosuite)_experts?\.json",
            "Scripted experts",
            render_experts,
            produced_by=("the experts", "the simulators"),
        ),
        Section(
            r"pusht_env\.json|robosuite_throughput_.*\.json",
            "Adapters against the raw simulator",
            render_sim_throughput,
            produced_by=("the simulators",),
        ),
    ],
}


def _load(path: Path) -> Any:
    return json.loads(path.read_text())


def _quick(data: Any) -> bool:
    """A --quick run's file: it checked a script, it measured nothing, so no section lists it."""
    return isinstance(data, dict) and bool(data.get("quick"))


def _render(render: Callable[[Any], str], arg: Any) -> str:
    try:
        return render(arg)
    except (KeyError, TypeError, ValueError) as err:  # an older layout of a file
        return f"Not rendered: an older layout of its file ({err!r}); re-run its script."


def _figures(path: Path) -> list[Path]:
    """The script's own figures of a results file: ``<stem>.png``, else ``<stem>_*.png``."""
    plot = path.with_suffix(".png")
    return [plot] if plot.is_file() else sorted(path.parent.glob(f"{path.stem}_*.png"))


def _status(section: Section, files: list[tuple[Path, dict]], repo: Path) -> SectionStatus:
    return section_status([(p.name, d) for p, d in files], section.produced_by, repo)


def _section(section: Section, files: list[tuple[Path, dict]], doc: Path, repo: Path = REPO) -> list[str]:
    """One published table under its heading: whether its code changed since it was measured (its
    status), then each source file, when and where it was measured."""
    status = _status(section, files, repo).line
    parts = [f"### {section.title}", ""]
    if section.merged:
        parts += [status, "", _render(section.render, [(p.name, d) for p, d in files]), ""]
        parts += ["Sources:", ""]
        # a file's own words follow its source line: one numbered item per file, its note beside it
        parts += [
            f"{i}. {source_line(p, d, doc)}" + (f" {d['note']}" if d.get("note") else "")
            for i, (p, d) in enumerate(files, 1)
        ]
        return [*parts, ""]
    # one source: its status and its line share a paragraph; several: the status heads them all
    lead = f"{status} " if len(files) == 1 else ""
    if not lead:
        parts += [status, ""]
    for path, data in files:
        body = _render(section.render, data)
        if data.get("note"):  # a file's own words after its table, whatever renders it
            # after prose they continue its paragraph; after a table they need their own
            body = body.rstrip()
            body += ("\n\n" if body.endswith("|") else " ") + data["note"]
        parts += [f"{lead}Source: {source_line(path, data, doc)}", "", body, ""]
        parts += [line for plot in _figures(path) for line in (f"![{plot.stem}]({link(plot, doc)})", "")]
    return parts


def _summary_parts(results: Path, doc: Path, level: str, overview_table: bool) -> list[str]:
    """The claims table, the overview table when asked for, and the overview figure."""
    from benchmarks.report import success_overview
    from benchmarks.report.claims import claims_table

    parts = []
    claims = claims_table(results)
    if claims:  # the digest first: each claim, its figures and a rule's verdict
        parts += [f"{level} The paper's claims, as measured here", "", claims, ""]
    overview = success_overview.overview_table(results) if overview_table else None
    if overview:  # every task's methods side by side, before each file's own section
        parts += [f"{level} Success across tasks (the paper's Table 2 and Figure 4)", "", overview, ""]
    if (results / OVERVIEW_PLOT).is_file():
        parts += [f"![Success across tasks]({link(results / OVERVIEW_PLOT, doc)})", ""]
    finetune = finetune_overview.overview_table(results) if overview_table else None
    if finetune:  # the headline arms of every fine-tuning start, before each file's own section
        parts += [f"{level} Fine-tuning at a glance", "", finetune, ""]
        figures = [
            f"![Fine-tuning: {start}]({link(path, doc)})"
            for start, path in zip(finetune_overview.HEADLINE, finetune_overview.figure_paths(results))
            if path.is_file()
        ]
        if figures:  # one line: the starts' figures side by side where the page is wide enough
            parts += [" ".join(figures), ""]
    return parts


def build_finetune_block(results: Path = RESULTS) -> str:
    """The README's fine-tuning block between its markers: the headline arms' table."""
    table = finetune_overview.overview_table(results) or "No fine-tuning results saved yet."
    return "\n".join([FT_BEGIN, "", table, "", FT_END])


def build_summary(results: Path = RESULTS, readme: Path = Path("README.md"), doc: Path = RESULTS_DOC) -> str:
    """The README's block between the markers: the claims table, the overview figure, a link to
    RESULTS.md."""
    parts = [BEGIN, "", *_summary_parts(results, readme, "###", overview_table=False)]
    parts += [f"Every figure, its source file and its machine: [{doc.name}]({link(doc, readme)}).", "", END]
    return "\n".join(parts)


def _published(results: Path) -> tuple[list[tuple[str, Section, list[tuple[Path, dict]]]], list[str]]:
    """Every published table with its files ((group, section, [(path, data)])), and the names of the
    files no section takes; quick-mode files are neither."""
    files = [(p, _load(p)) for p in sorted(results.glob("*.json"))]
    files = [(p, d) for p, d in files if not _quick(d)]
    found, rendered = [], set()
    for group, entries in GROUPS.items():
        for section in entries:
            matched = [
                (p, d) for p, d in files if p.name not in rendered and re.fullmatch(section.pattern, p.name)
            ]
            if matched:
                rendered.update(p.name for p, _ in matched)
                found.append((group, section, matched))
    return found, [p.name for p, _ in files if p.name not in rendered]


def code_stale_sections(results: Path = RESULTS, repo: Path = REPO) -> list[tuple[str, SectionStatus]]:
    """The published tables whose producing code changed after their files' commits: (title,
    status), the status naming each file and the first commit that changed it
    (:mod:`~benchmarks.report.staleness`). Files that record no commit are not among them."""
    found, _ = _published(results)
    statuses = [(section.title, _status(section, files, repo)) for _, section, files in found]
    return [(title, status) for title, status in statuses if status.state == "stale"]


def build_results(results: Path = RESULTS, doc: Path = RESULTS_DOC, repo: Path = REPO) -> str:
    """The whole of RESULTS.md: the summary, then one section per published table in its group, each
    with its status against the code of ``repo`` (a git checkout)."""
    from benchmarks.report.defaults_evidence import evidence_table

    found, unrendered = _published(results)
    sections: dict[str, list[str]] = {group: [] for group in GROUPS}
    for group, section, matched in found:
        sections[group] += _section(section, matched, doc, repo)
    parts = [
        "# Results",
        "",
        f"Generated by `python -m benchmarks.report` from the JSON files under `{results.as_posix()}/`: no "
        "number here is typed by hand, and `python -m benchmarks.report --check` (run in CI) fails, naming "
        "the section, when this file differs from what those files give, and when the code that produces "
        "a section changed after the commit its files were measured at (its status: stale). Each section "
        "names its source files, when they were measured and on what machine (files saved before the "
        'scripts recorded the time, command and commit say "not recorded"; such a section is unverified: '
        "it cannot be dated against the code). The scripts that write them: "
        "[benchmarks/README.md](README.md).",
        "",
        "## Summary",
        "",
        *_summary_parts(results, doc, "###", overview_table=True),
    ]
    for group, section in sections.items():
        if section:
            parts += [f"## {group}", "", *section]
    evidence = evidence_table(results)
    if evidence:
        parts += ["## Defaults and the measurements behind them", "", evidence, ""]
    if unrendered:
        parts += ["## Other saved results", ""]
        parts += ["No section yet: " + ", ".join(f"`{n}`" for n in unrendered) + ".", ""]
    return "\n".join(parts).rstrip("\n") + "\n"


def _sections(text: str) -> dict[str, str]:
    """Markdown text by heading ("(top)" before the first): the unit --check names."""
    found: dict[str, list[str]] = {"(top)": []}
    current = "(top)"
    for line in text.splitlines():
        if line.startswith("#"):
            current = line.lstrip("#").strip()
            found.setdefault(current, [])
        found[current].append(line)
    return {k: "\n".join(v) for k, v in found.items()}


def stale_sections(old: str, new: str) -> list[str]:
    """Headings whose text differs between ``old`` and ``new``, or that only one of them has."""
    a, b = _sections(old), _sections(new)
    names = list(b) + [k for k in a if k not in b]
    stale = [k for k in names if a.get(k) != b.get(k)]
    if not stale and old != new:  # same sections, different order
        stale = ["(the order of the sections)"]
    return stale


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--readme", default="README.md")
    parser.add_argument("--results", default=str(RESULTS), help="the folder of saved JSON")
    parser.add_argument("--out", default=str(RESULTS_DOC), help="the generated results document")
    parser.add_argument(
        "--check",
        action="store_true",
        help="exit 1 when RESULTS.md or the README's summary differs, or a section's code changed since "
        "its files were measured",
    )
    parser.add_argument(
        "--repo", default=str(REPO), help="the git checkout whose history dates the files (default: this one)"
    )
    args = parser.parse_args(argv)
    readme, results, out, repo = Path(args.readme), Path(args.results), Path(args.out), Path(args.repo)
    text = readme.read_text()
    if BEGIN not in text or END not in text:
        print(f"{readme}: no results markers ({BEGIN} ... {END}); add them where the summary goes")
        return 2
    if not args.check:  # the figure is drawn from the same files; --check only reads
        from benchmarks.report.success_overview import overview_figure

        overview_figure(results, results / OVERVIEW_PLOT)
        finetune_overview.overview_figures(results)
    summary = build_summary(results, readme, out)
    blocks = [(BEGIN, END, summary, "the results summary")]
    if FT_BEGIN in text and FT_END in text:
        blocks.append((FT_BEGIN, FT_END, build_finetune_block(results), "the fine-tuning table"))
    new_readme, stale_blocks = text, []
    for begin, end, block, what in blocks:
        old_block = new_readme[new_readme.index(begin) : new_readme.index(end) + len(end)]
        if old_block != block:
            stale_blocks.append(what)
        new_readme = new_readme.replace(old_block, block)
    new_doc = build_results(results, out, repo)
    if args.check:
        problems = [f"{readme}: {what} between the markers is out of date" for what in stale_blocks]
        if not out.is_file():
            problems.append(f"{out}: missing")
        elif stale := stale_sections(out.read_text(), new_doc):
            problems.append(f"{out}: out of date in " + "; ".join(f"'{s}'" for s in stale))
        if problems:
            problems.append("run python -m benchmarks.report to rebuild them from the saved JSON")
        stale_code = code_stale_sections(results, repo)
        for title, status in stale_code:
            reasons = "; ".join(status.reasons)
            problems.append(f"{out}: '{title}' is stale, its code changed since it was measured: {reasons}")
        if stale_code:
            problems.append(
                "re-measure each stale section (its files' commands), or, where a change moves no figure, "
                f"say so in its commit message with a '{TRAILER} <why>' line"
            )
        for problem in problems:
            print(problem)
        return 1 if problems else 0
    readme.write_text(new_readme)
    out.write_text(new_doc)
    print(f"{out} and the summary in {readme} rebuilt from {results}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
