"""The RESULTS.md sections of speed (``benchmarks/speed/``): per-chunk latency of every sampler (all
``latency*.json`` in one table), CUDA capture, the image policy, the training step, the exported policy,
and the simulators' throughput against the raw simulator."""

from __future__ import annotations

from benchmarks.report.tables import num, table

__all__ = [
    "render_env_throughput",
    "render_export_latency",
    "render_image_latency",
    "render_image_train",
    "render_latency",
    "render_latency_cuda",
    "render_network_cost",
    "render_sampler",
    "render_sim_throughput",
    "render_train_throughput",
]

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


def _dims(network: dict) -> str:
    return "/".join(map(str, network.get("down_dims", [])))


def _denoiser(network: dict) -> str:
    """``UNet 64/128/256`` or ``MLP 512/512/512/512``."""
    if network.get("name") == "mlp":
        return "MLP " + "/".join(map(str, network.get("hidden_dims", [])))
    return f"UNet {_dims(network)}"


def _latency_label(network: dict) -> str:
    """A latency file's column name: its task (image), else ``mlp`` or ``state`` (the UNet)."""
    return network.get("task") or ("mlp" if network.get("name") == "mlp" else "state")


def render_latency(files: list[tuple[str, dict]]) -> str:
    """Every latency file in one table: a column per (network, device, batch), a row per sampler,
    each cell the per-chunk wall ms and its multiple of L1 Flow's in the same run."""
    columns, methods = [], {}
    for _, d in files:
        net, device = d.get("network") or {}, d["machine"].get("device", "cpu")
        for batch, block in d["inference"].items():
            columns.append((f"{_latency_label(net)}, {device}, {batch}", d, block))
            for method in block["ms"]:
                methods.setdefault(method, d["nfe"].get(method))
    header = ["method", "NFE"] + [title for title, _, _ in columns]
    rows = [
        [method, nfe]
        + [
            f"{num(b['ms'][method]['wall_ms'])} ({num(b['slowdown_vs_l1flow'][method])}×)"
            if method in b["ms"]
            else "–"
            for _, _, b in columns
        ]
        for method, nfe in methods.items()
    ]
    rows.append(["L1 Flow over its floor", "–"] + [f"{b['l1flow_over_floor']}×" for _, _, b in columns])
    nets = {_latency_label(d.get("network") or {}): d.get("network") or {} for _, d in files}
    out = [
        "Per-chunk wall ms (its multiple of L1 Flow's in the same run); CPU ms are in the files. Networks: "
        + "; ".join(
            f"{task} ({num(n.get('parameters'))} parameters, {_denoiser(n)})" for task, n in nets.items()
        )
        + ". The floor: the encoder and 2 network forwards. cp1/cp3: Consistency Policy at 1 and 3 steps; "
        "onedp1: OneDP's one-step generator; edm_heun18/10: EDM's Heun sampler over 18/10 levels.",
        "",
        table(header, rows),
    ]
    for name, d in files:
        if "train_step_ms" in d:
            t = d["train_step_ms"]
            rows = [[k, v["wall_ms"], v["cpu_ms"]] for k, v in t["ms"].items()]
            out += [
                "",
                f"Training step, batch {t['batch']} (`{name}`):",
                "",
                table(["loss", "wall ms", "CPU ms"], rows),
            ]
    return "\n".join(out)


def render_latency_cuda(d: dict) -> str:
    """bench_latency_cuda: batch-1 chunks on the GPU, eager and captured, against diffusers' loops."""
    out = []
    if d.get("cudnn_benchmark"):
        out.append("cuDNN autotuning on (every arm).\n")
    for name, block in d["networks"].items():
        rows = [[method, ms["wall_ms"], block["chunks_per_s"][method]] for method, ms in block["ms"].items()]
        out.append(f"{name} network ({num(block['parameters'])} parameters), batch 1:\n")
        out.append(table(["method", "wall ms", "chunks/s"], rows))
        ratios = [
            f"{key.replace('_', ' ')} {block[key]}×"
            for key in (
                "cuda_graph_speedup_over_eager",
                "cuda_graph_speedup_over_diffusers_ddpm100",
                "cuda_graph_speedup_over_diffusers_ddim16",
                "eager_speedup_over_diffusers_ddpm100",
                "eager_speedup_over_diffusers_ddim16",
            )
            if key in block
        ]
        out.append("\n" + "; ".join(ratios) + ".\n")
        for key, err in block.get("errors", {}).items():
            out.append(f"{key}: not measured ({err})\n")
    return "\n".join(out)


def render_image_latency(d: dict) -> str:
    rows = [
        [
            batch,
            b["ms"]["actor"]["wall_ms"],
            b["ms"]["actor"]["cpu_ms"],
            b["ms"]["floor"]["cpu_ms"],
            b["actor_over_floor"],
        ]
        for batch, b in d["inference"].items()
    ]
    return table(["batch", "actor wall ms", "actor CPU ms", "floor CPU ms", "actor / floor (wall)"], rows)


def render_image_train(d: dict) -> str:
    s = d["setup"]
    return table(
        ["batch", "image", "samples/s from the buffer", "samples/s resident", "buffer / resident"],
        [
            [
                s["batch"],
                "×".join(map(str, s["image"])),
                d["samples_per_s"]["buffer"],
                d["samples_per_s"]["resident"],
                d["buffer_over_resident"],
            ]
        ],
    )


def render_train_throughput(d: dict) -> str:
    rows = []
    for net, block in d["networks"].items():
        for setting, r in block["settings"].items():
            rows.append(
                [
                    net,
                    setting,
                    r["samples_per_s"]["trainer"],
                    r["samples_per_s"]["model"],
                    r["trainer_over_model"],
                ]
            )
    text = table(["network", "setting", "trainer samples/s", "bare update samples/s", "trainer / bare"], rows)
    return text


def render_env_throughput(d: dict) -> str:
    rows = []
    for r in d["rows"]:
        for name, a in r["adapters"].items():
            rows.append([r["setting"], name, r["raw_steps_per_s"], a["steps_per_s"], a["over_raw"]])
    return table(["setting", "adapter", "raw steps/s", "adapter steps/s", "× raw"], rows)


def render_sampler(d: dict) -> str:
    return table(
        ["storage", "chunks/s sampled", "× training rate"],
        [
            ["state", d["state_chunks_per_s"], d["state_sampler_over_train"]],
            ["rgb 128²", d["rgb128_chunks_per_s"], d["rgb128_sampler_over_train"]],
        ],
    )


def render_sim_throughput(d: dict) -> str:
    """Adapter against the raw simulator, steps/s (PushT's per-task blocks or robosuite's rows)."""
    if "rows" in d:
        rows = [
            [r["setting"], r["raw_steps_per_s"], r["make_env_steps_per_s"], r["make_env_over_raw"]]
            for r in d["rows"]
        ]
        return table(["setting", "raw steps/s", "make_env steps/s", "× raw"], rows)
    rows = []
    for task, block in d.items():
        if isinstance(block, dict) and "steps_per_s" in block:
            for name, rate in block["steps_per_s"].items():
                rows.append([task, name, rate, block["ratio_to_raw"][name]])
    return table(["task", "setting", "steps/s", "× raw"], rows)


def render_network_cost(data: dict) -> str:
    """The state denoisers side by side: one training step and one 2-NFE chunk, each network's wall
    ms and the MLP's multiple of the UNet's in the same run."""
    figs, d = data["figures"], data["data"]
    names = list(figs)
    lines = [
        f"State observations {d['obs_dim']}-D, {d['action_dim']}-D actions, training batch "
        f"{d['train_batch']}; {data['repetitions']['statistic']} over the repetitions; ratio = MLP over UNet "
        "in the same run.",
        "",
        "| figure | "
        + " | ".join(f"{n} ({figs[n]['parameters'] / 1e6:.2f}M params)" for n in names)
        + " | ratio |",
        "|---|" + "---|" * (len(names) + 1),
    ]
    rows = [
        ("training step, " + k.replace("_", " "), "train_step_ms", k) for k in figs[names[0]]["train_step_ms"]
    ]
    rows += [("2-NFE chunk, " + k.replace("_", " "), "chunk_ms", k) for k in figs[names[0]]["chunk_ms"]]
    for label, group, key in rows:
        values = [figs[n][group][key] for n in names]
        ratio = values[-1] / values[0] if values[0] else float("nan")
        lines.append(f"| {label} (ms) | " + " | ".join(f"{v:.3g}" for v in values) + f" | {ratio:.3f} |")
    goals = data.get("goals", {})
    if goals:
        lines += [
            "",
            f"MLP training step {goals['train_step_speedup_1_thread']:.1f}x faster than the UNet's on one "
            "thread (goal >= 10x); MLP chunk rate at batch 1 "
            f"{goals['mlp_chunk_rate_hz_batch1_1_thread']:.0f} Hz on one thread (goal >= 1 kHz).",
        ]
    return "\n".join(lines)
