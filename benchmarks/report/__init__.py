"""The report: ``python -m benchmarks.report`` rebuilds ``benchmarks/RESULTS.md`` and the README's
generated blocks from ``benchmarks/results/``; ``--check`` (run in CI) fails on a stale one.

:mod:`.build` assembles the document and runs the command; :mod:`.success`, :mod:`.speed` and
:mod:`.finetune` render their groups' tables; :mod:`.claims`, :mod:`.success_overview` and
:mod:`.finetune_overview` the summary; :mod:`.defaults_evidence` the measurements behind defaults.
"""

from benchmarks.report.build import (
    BEGIN,
    END,
    FT_BEGIN,
    FT_END,
    GROUPS,
    RESULTS,
    RESULTS_DOC,
    Section,
    build_finetune_block,
    build_results,
    build_summary,
    main,
    stale_sections,
)

__all__ = [
    "BEGIN",
    "END",
    "FT_BEGIN",
    "FT_END",
    "GROUPS",
    "RESULTS",
    "RESULTS_DOC",
    "Section",
    "build_finetune_block",
    "build_results",
    "build_summary",
    "main",
    "stale_sections",
]
