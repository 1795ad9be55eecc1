#!/usr/bin/env bash
# The wheels a lent GPU machine lacks for plenocl, into .whl/ at the checkout's root
# (ignored by git; the `device` tool's run carries it: `carry: [".whl"]`).
#
#     bash benchmarks/device_wheels.sh
#
# The machine (the device tool's nvidia-h200) has Python 3.12, no network, and an image
# holding NumPy, SciPy, scikit-image, matplotlib, pytest and much else, but not pyopencl
# or the chain's other dependencies. pip resolves those here for CPython 3.12 on
# manylinux x86-64; the wheels of packages the image already holds are dropped (its own
# versions are used), which keeps .whl/ near 36 MB of the run's 64 MiB. Then
# `benchmarks/device_check.sh` installs them there.
set -euo pipefail
cd "$(dirname "$0")/.."
exclude=$(git rev-parse --git-path info/exclude)
grep -qx '/.whl/' "$exclude" 2>/dev/null || echo '/.whl/' >> "$exclude"
rm -rf .whl && mkdir .whl
# pyproject.toml's dependencies that the image lacks (their own needs resolved by pip)
wanted=("pyopencl>=2023.1" "imagecodecs>=2023.1" "tomli-w>=1.0" "pyevtk>=1.6"
        "pyfftw>=0.13" "dask[distributed]>=2024.1" "zarr>=3.0" "platformdirs>=3.0")
platforms=()
for tag in manylinux_2_17 manylinux2014 manylinux_2_24 manylinux_2_27 manylinux_2_28 \
           manylinux_2_31 manylinux_2_34 manylinux_2_35; do
    platforms+=(--platform "${tag}_x86_64")
done
python3 -m pip download -q --only-binary=:all: --python-version 3.12 --implementation cp \
    "${platforms[@]}" -d .whl "${wanted[@]}"
# in the image (the device tool's KINDS.md, "Python packages already there")
image="numpy scipy scikit_image matplotlib pillow imageio tifffile networkx lazy_loader
contourpy cycler fonttools kiwisolver pyparsing python_dateutil six packaging jinja2
markupsafe click cloudpickle fsspec toolz msgpack psutil pyyaml sortedcontainers tqdm
threadpoolctl typing_extensions urllib3 zipp"
for name in $image; do
    rm -f .whl/"$name"-*.whl
done
ls .whl
du -sh .whl
