"""The control behind Square's turned shifted replays (record.json): the same attempts (scene seeds
and source draws) played translated only, from the nearest source (``translate_nearest``) or from
any source (``translate_uniform``). Run from the repository root:
``python benchmarks/run_records/square_shift_turn/translate_control.py translate_nearest 100``."""

import json
import sys
from pathlib import Path

import h5py

import l1flow_rl.experts.robosuite.shifted as sh
from l1flow_rl.config import load_task_config

BASE = Path("data/robosuite/NutAssemblySquare/NutAssemblySquare.absolute.state.seed0.n50.hdf5")


def main(mode: str, attempts: int) -> None:
    body = sh.SHIFTED_OBJECTS["NutAssemblySquare"].body
    translated = sh.ShiftedObject(body, turns=False)
    if mode == "translate_uniform":
        sh.SHIFTED_OBJECTS["NutAssemblySquare"] = translated
    elif mode == "translate_nearest":
        turned_replay = sh.shifted_replay

        def replay(env, task, sources, seed, draw):
            # the turned run's choice of source, played with the turning switched off
            sh.sim.seed_episode(env, seed)
            env.reset()
            source = sh.nearest_sources(sources, *sh.object_pose(env, task.env_id))[draw]
            sh.SHIFTED_OBJECTS["NutAssemblySquare"] = translated
            try:
                return turned_replay(env, task, [source], seed, 0)
            finally:
                sh.SHIFTED_OBJECTS["NutAssemblySquare"] = sh.ShiftedObject(body, turns=True)

        sh.shifted_replay = replay  # workers=1 plays in this process, so the patch applies
    else:
        raise SystemExit(f"mode {mode!r}: expected translate_nearest or translate_uniform")
    task = load_task_config("robosuite_square")
    out = sh.add_shifted_replays(
        task, BASE, Path(f"/tmp/square_{mode}.hdf5"), attempts, workers=1, progress=False
    )
    with h5py.File(out) as f:
        print(mode, json.loads(f["data"].attrs["shifted_replays"]))


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]))
