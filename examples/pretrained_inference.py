"""Run a pretrained policy folder on a stream of observations, receding horizon, with no simulator.

The loop a robot runs: keep the last To observations, ask the policy for a chunk when the previous
chunk's K actions are used up, send one action per control step. The policy comes either from the
folder's weights (``L1FlowActor.from_pretrained``) or from its exported program (``policy.pt2``,
loaded with torch alone); both give the same actions for the same noise.

Observations come from a demonstration file (``--observations``, anything ``load_episodes`` reads: the
stream is its first episode) or, without one, from a synthetic sensor of the right shapes.

    python examples/pretrained_inference.py runs/policy --steps 40
    python examples/pretrained_inference.py runs/policy --program --observations demos/PushT.zarr

Make a folder with ``l1flow-rl export checkpoint=runs/.../checkpoints/best.pt out=runs/policy program=true``.
"""

from __future__ import annotations

import argparse
import sys
from collections import deque
from collections.abc import Iterator
from pathlib import Path

import torch
from tensordict import TensorDict

from l1flow_rl import L1FlowActor
from l1flow_rl.export.pretrained import read_pretrained_config


def synthetic_stream(config: dict, steps: int, seed: int = 0) -> Iterator[dict[str, torch.Tensor]]:
    """One observation per step, {entry: tensor of its per-step shape}: a slow random walk for flat
    entries, noise images for cameras."""
    g = torch.Generator().manual_seed(seed)
    entries = config["observation"]["entries"]
    state = {k: torch.randn(*e["shape"], generator=g) for k, e in entries.items() if e["dtype"] != "uint8"}
    for _ in range(steps):
        obs = {}
        for name, entry in entries.items():
            if entry["dtype"] == "uint8":
                obs[name] = torch.randint(0, 256, tuple(entry["shape"]), dtype=torch.uint8, generator=g)
            else:
                state[name] = state[name] + 0.05 * torch.randn(*entry["shape"], generator=g)
                obs[name] = state[name].clone()
        yield obs


def recorded_stream(path: str, config: dict) -> Iterator[dict[str, torch.Tensor]]:
    """The observations of the first episode of a demonstration file, as {entry: tensor}."""
    from l1flow_rl.data import load_episodes

    episodes = load_episodes(path)
    first = episodes[episodes["episode"] == episodes["episode"][0]]
    observation = first["observation"]
    for t in range(first.shape[0]):
        step = observation[t]
        if isinstance(step, torch.Tensor):
            yield {"state": step}
        else:
            yield {k: step[k] for k in config["observation"]["entries"]}


def run(
    folder: str | Path,
    observations: Iterator[dict[str, torch.Tensor]],
    *,
    program: bool = False,
    seed: int = 0,
) -> tuple[torch.Tensor, int]:
    """Act on every observation of the stream; returns (actions [T, A], number of chunks computed)."""
    folder = Path(folder)
    config = read_pretrained_config(folder)
    horizon = config["policy"]["obs_horizon"]
    names = list(config["observation"]["entries"])
    if program:
        # torch alone: no l1flow_rl, no TensorDict needed to run this
        policy = torch.export.load(str(folder / config["program"]["file"])).module()
    else:
        actor = L1FlowActor.from_pretrained(folder)

        def policy(*inputs):
            *entries, noise = inputs
            obs = entries[0] if names == ["state"] else TensorDict(dict(zip(names, entries)), batch_size=[1])
            return actor.policy(obs, noise=noise)

    pred_horizon, action_dim = config["action"]["predicted_chunk"]
    g = torch.Generator().manual_seed(seed)
    history: deque[dict[str, torch.Tensor]] = deque(maxlen=horizon)
    queue: deque[torch.Tensor] = deque()
    actions, chunks = [], 0
    with torch.inference_mode():
        for obs in observations:
            history.append(obs)
            while len(history) < horizon:  # at the start, the first observation stands in for the past
                history.appendleft(obs)
            if not queue:  # the previous chunk is used up: plan again from the latest observations
                entries = [torch.stack([h[k] for h in history])[None] for k in names]  # [1, To, ...]
                noise = torch.randn(1, pred_horizon, action_dim, generator=g)
                queue.extend(policy(*entries, noise)[0])  # K actions
                chunks += 1
            actions.append(queue.popleft())  # send to the robot here
    return torch.stack(actions), chunks


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("folder", help="a pretrained folder (l1flow-rl export)")
    parser.add_argument("--steps", type=int, default=40, help="control steps of the synthetic stream")
    parser.add_argument("--observations", help="a demonstration file to replay observations from")
    parser.add_argument("--program", action="store_true", help="run policy.pt2 instead of the weights")
    args = parser.parse_args(argv)
    config = read_pretrained_config(args.folder)
    stream = (
        recorded_stream(args.observations, config)
        if args.observations
        else synthetic_stream(config, args.steps)
    )
    actions, chunks = run(args.folder, stream, program=args.program)
    print(f"{len(actions)} actions from {chunks} chunks; first: {actions[0].tolist()}")
    print(f"last: {actions[-1].tolist()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
