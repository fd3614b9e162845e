#!/bin/bash
# Rebuilds what call1.sh carries (run here, in the repository root; ~2 minutes): .gpu/core312.tar.xz (the
# Python 3.12 packages the device image lacks, robosuite pruned to PickPlaceCan's files), .gpu/can_start.pt
# (the mixed-30 Can BC start, its EMA weights only), .gpu/can_mixed30.hdf5.xz (its data) and .gl/ (GL loaders for MuJoCo's EGL renderer).
# Changed from ../device14/build_bundle.sh: the start is runs/ft_bc_can_mixed30 (test 0.40), and diffusers is
# no longer carried (the core imports none of it since l1flow_rl/flow/diffusion_schedule.py).
# Needs the .venv and runs/ft_bc_can_mixed30 (l1flow-rl train task=robosuite_can demos=mixed demos.num=30
# train.steps=3000 eval.episodes=100 seed=0 run_dir=runs/ft_bc_can_mixed30).
set -euo pipefail
grep -qx "/.gpu/" .git/info/exclude 2>/dev/null || echo "/.gpu/" >> .git/info/exclude
grep -qx "/.gl/" .git/info/exclude || echo "/.gl/" >> .git/info/exclude
B=$(mktemp -d) && rm -rf .gpu .gl && mkdir -p .gpu .gl
plat="--platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64"
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp $plat -d $B/whl \
    tensordict==0.14.3 torchrl==0.14.1 hoptorch==0.1.4 pyvers==0.2.3 orjson==3.13.0 hydra-core==1.3.8 \
    omegaconf==2.3.1 gymnasium==1.4.0 farama-notifications==0.0.6 importlib-metadata==10.2.0 \
    robosuite==1.5.2 mujoco==3.3.7 zarr==3.1.5 numcodecs==0.16.6 donfig==0.8.1.post1 google-crc32c==1.9.0 \
    termcolor==3.3.0 glfw==2.11.0 pyopengl==3.1.10
python3 -m pip wheel -q --no-deps -w $B/whl antlr4-python3-runtime==4.9.3  # an sdist only on PyPI
python3 -m pip install -q --no-deps --no-index --target $B/site --python-version 3.12 --only-binary=:all: $plat $B/whl/*.whl
# robosuite's assets are 526 MB: keep every XML/JSON and only the meshes and textures PickPlaceCan loads
.venv/bin/python - "$B/site" <<'PY'
import os, re, sys
import robosuite as suite
env = suite.make("PickPlaceCan", robots=["Panda"], has_renderer=False, has_offscreen_renderer=False,
                 use_camera_obs=False)
need = {os.path.normpath(f.split("/site-packages/")[1]) for f in re.findall(r'file="([^"]+)"', env.model.get_xml())}
site = sys.argv[1]
for d, _, files in os.walk(os.path.join(site, "robosuite/models/assets")):
    for f in files:
        p = os.path.join(d, f)
        keep = os.path.relpath(p, site) in need or (f.endswith((".xml", ".json")) and "bullet_data" not in p)
        if not keep:
            os.remove(p)
PY
# zarr (and its codecs) is imported only by the Diffusion Policy zarr format, torchrl's examples never:
# dropped so that the tree (22.4 MB by the twenty-fourth session) and the bundle stay under 64 MiB
(cd $B/site && rm -rf numcodecs* zarr* donfig* google_crc32c* sota-implementations)
tar -cf - -C $B/site . | xz -6 -T2 > .gpu/core312.tar.xz
.venv/bin/python - <<'PY'
import torch
ck = torch.load("runs/ft_bc_can_mixed30/checkpoints/best.pt", weights_only=True, map_location="cpu")
ck["model"], ck["optimizer"] = ck["ema"], {}  # one copy of the weights travels (torch.save shares the storages)
torch.save(ck, ".gpu/can_start.pt")
PY
# the start's 30 demonstrations (QC's offline half), xz-compressed: 7.4 MB -> 1.8 MB, under the 64 MiB a call carries
xz -6 -T2 -c data/robosuite/PickPlaceCan/PickPlaceCan.absolute.state.seed0.n30.mixed.hdf5 > .gpu/can_mixed30.hdf5.xz
o='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64'
mkdir -p /tmp/amd64/partial && apt-get $o update -qq && (cd .gl && apt-get $o download -qq libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2)
rm -rf $B && ls -la .gpu .gl
