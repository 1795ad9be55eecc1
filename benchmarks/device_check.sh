#!/usr/bin/env bash
# Issue 46's GPU checks as one prepared command for a lent machine (the `device` tool):
# the device's kernels against their NumPy twins, the paper-size pair's profile and a
# 20-pair batch, each printed and kept under $OUT.
#
#     bash benchmarks/device_check.sh [tests] [pair] [batch]     (all three by default)
#
# Prepare here first: `bash benchmarks/device_wheels.sh` (the wheels the machine lacks,
# in .whl/), then run there with `carry: [".whl"]` and a timeout that leaves time to
# rerun (on an H200 on 2026-12-04, from each section's start and exit lines: the pair
# 32 s, the batch 74 s, the tests 46 s; each call about 10 s more for the install and
# the device list, and about 30 s for the machine's start; docs/design.md §7.5). Each
# section's start and exit lines are kept in its file too. The device is plenocl's
# choice (a GPU first) unless PYOPENCL_CTX names one. PY: the Python to use (default
# python3); LENSES: the camera's microlenses (default the whole sensor, "289 193");
# PAIRS: the batch's counts (default "4 20", with 12 Dask workers sharing the device, as
# on 2026-11-30); WHEELS: the wheels' folder (default .whl; empty: install none).
# The image's loader lists only PoCL: plenocl registers NVIDIA's OpenCL library itself
# (plenocl.opencl.icd, since 2026-12-04); if the default device is still not NVIDIA's,
# this script writes /etc/OpenCL/vendors/nvidia.icd, as the 2026-11-30 run did, and
# stops if even then it is not, rather than measure a CPU on the GPU's time.
set -uo pipefail
cd "$(dirname "$0")/.."
out=${OUT:-/tmp/plenocl-device-check}
mkdir -p "$out"
export PYTHONUNBUFFERED=1
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
py=${PY:-python3}
wheels=${WHEELS-.whl}  # WHEELS= (empty): none installed, the Python's own packages
if [ -n "$wheels" ] && [ -d "$wheels" ]; then
    "$py" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
        --target /tmp/site "$wheels"/*.whl || exit 1
    export PYTHONPATH=$PWD:/tmp/site
fi
# NVIDIA's OpenCL library, where the machine has one
lib=$(ldconfig -p 2>/dev/null | awk '/libnvidia-opencl\.so.*x86-64/{print $NF; exit}')
[ -n "$lib" ] || lib=$(ls /usr/local/nvidia/lib64/libnvidia-opencl.so* 2>/dev/null | head -1)
lenses=${LENSES:-289 193}
sections=("$@")
[ ${#sections[@]} -gt 0 ] || sections=(tests pair batch)
status=0
run() {  # name, then the command; its output printed and kept as $out/name.txt
    local name=$1
    shift
    echo "== $name: $* ($(date -u +%T))" | tee "$out/$name.txt"
    "$@" 2>&1 | tee -a "$out/$name.txt"
    local rc=${PIPESTATUS[0]}
    echo "== $name: exit $rc ($(date -u +%T))" | tee -a "$out/$name.txt"
    [ "$rc" -eq 0 ] || status=1
}
run devices "$py" -m plenocl devices
nvidia_default() { grep -q "^default: .*NVIDIA" "$out/devices.txt"; }
# plenocl registers the library it finds itself; this helps where it sits elsewhere
if [ -n "$lib" ] && [ -z "${PYOPENCL_CTX:-}" ] && ! nvidia_default &&
   ! grep -qs nvidia-opencl /etc/OpenCL/vendors/*.icd; then
    echo "== plenocl did not make NVIDIA's library ($lib) a platform: writing its .icd"
    mkdir -p /etc/OpenCL/vendors && echo "$lib" > /etc/OpenCL/vendors/nvidia.icd
    run devices "$py" -m plenocl devices
fi
if [ -n "$lib" ] && [ -z "${PYOPENCL_CTX:-}" ] && ! nvidia_default; then
    echo "NVIDIA's OpenCL library ($lib) is here but the default device is not NVIDIA's:"
    echo "check /etc/OpenCL/vendors and PYOPENCL_CTX before measuring"
    exit 3
fi
for section in "${sections[@]}"; do
    case $section in
        tests) run tests "$py" -m pytest -q -p no:cacheprovider -x -n 4 \
                   tests/test_devicebundle.py tests/test_fitsums.py tests/test_sightlines.py \
                   tests/test_device_peaks.py tests/test_device_volume.py \
                   tests/test_deviceimage.py tests/test_piv_devicefft.py \
                   tests/test_rowlists.py tests/test_projector.py ;;
        pair) run pair "$py" benchmarks/paper_pair.py --lenses $lenses --bit-depth 16 \
                  --settings default --profile --host-profile 40 --bytes-by-site 15 ;;
        batch) run batch "$py" benchmarks/throughput.py --lenses $lenses \
                   --pairs ${PAIRS:-4 20} --workers 12 ;;
        *) echo "unknown section $section (tests, pair, batch)"; exit 2 ;;
    esac
done
exit $status
