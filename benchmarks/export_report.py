"""The RESULTS.md section of ``export_latency.json`` (``bench_export_latency``): one table per network.

For ``benchmarks.report``'s ``GROUPS["Speed: inference and training"]``, the entry
``(r"export_latency\\.json", "Deployable policy: exported program and ONNX", render_export_latency)``.
"""

from __future__ import annotations

__all__ = ["render_export_latency"]

_PATHS = {
    "eager_actor": "eager `L1FlowActor` (TensorDict)",
    "eager_policy": "eager `actor.policy(obs, noise=...)`",
    "exported": "`torch.export` program (`policy.pt2`)",
    "onnxruntime": "ONNX in onnxruntime",
}


def render_export_latency(data: dict) -> str:
    lines = [
        f"Batch {data['batch']}, {data['device']}, median of {data['rounds']} rounds; ratio = wall time over "
        "the eager actor's in the same run; max |diff| = largest difference from eager's actions for the "
        "same noise.",
        "",
    ]
    for network, block in data["networks"].items():
        lines += [
            f"**{network} network**",
            "",
            "| path | wall ms | CPU ms | ratio to eager actor | max abs diff |",
            "|---|---|---|---|---|",
        ]
        for name, row in block["paths"].items():
            diff = row.get("max_abs_diff_from_eager")
            shown = "" if diff is None else f"{diff:.2g}"
            lines.append(
                f"| {_PATHS.get(name, name)} | {row['wall_ms']:.3g} | {row['cpu_ms']:.3g} | "
                f"{row['ratio_to_eager_actor']:.2f} | {shown} |"
            )
        lines.append("")
    return "\n".join(lines).rstrip("\n")
