#!/usr/bin/env bash
# Run the warp decoder's tests and benchmark on the GPU machine of the device tool.
#
# The GPU image has numpy and pytest but not warp-lang, and warp's wheel is larger than one device
# call may carry (64 MiB with the working tree). So `pack` (here) tars the installed warp package
# without what CUDA runs do not need (warp-clang.so, the CPU backend's LLVM; tests; examples),
# compresses it with xz and splits it into two parts of at most 44 MiB under .gpuwarp/ (ignored by
# git through .git/info/exclude). Everything else the run needs is numpy + warp: the stadium crowd
# is generated in-process (samples/stadium_crowd.py) and the synthetic animation by vbusd.bake.
#
#   here:        bash benchmarks/gpu_run.sh pack
#   device call: carry [".gpuwarp/p1"]  command: bash benchmarks/gpu_run.sh stage 1
#   device call: carry [".gpuwarp/p2"]  command: bash benchmarks/gpu_run.sh stage 2 && bash benchmarks/gpu_run.sh run
#   (the second call within ~30 s of the first, while the machine is warm; a later call on the
#    same warm machine needs only `bash benchmarks/gpu_run.sh run`)
#
# `run` writes to $OUT: gpu.txt (nvidia-smi), pytest.log, conformance.log, bench.log, decoder_cuda.json, hardware.log,
# hardware.json. Kept in benchmarks/results/ as decoder_cuda[_h100].json,
# decoder_hardware_cuda.json (one file: both GPUs gave it byte for byte) and warp_tests_cuda_h100.log (no suffix: the H200 runs).
set -euo pipefail
cmd=${1:?usage: gpu_run.sh pack|stage N|run|layers}
case "$cmd" in
pack)
    site=$(python3 -c 'import os, warp; print(os.path.dirname(os.path.dirname(warp.__file__)))')
    exclude="$(git rev-parse --git-dir)/info/exclude"; mkdir -p "$(dirname "$exclude")"
    grep -qx '/.gpuwarp/' "$exclude" 2>/dev/null || echo '/.gpuwarp/' >> "$exclude"
    rm -rf .gpuwarp && mkdir -p .gpuwarp
    tar -C "$site" --exclude='__pycache__' --exclude='warp/tests' --exclude='warp/examples' \
        --exclude='warp/bin/warp-clang.so' -cf - warp | xz -T0 -6 | split -b 44m -d - .gpuwarp/part
    n=0
    for f in .gpuwarp/part*; do n=$((n + 1)); mkdir -p .gpuwarp/p$n; mv "$f" .gpuwarp/p$n/; done
    ls -l .gpuwarp/p*
    ;;
stage)
    mkdir -p /tmp/gw && cp ".gpuwarp/p$2"/* /tmp/gw/ && ls -l /tmp/gw
    ;;
run)
    if [ ! -d /tmp/site/warp ]; then
        mkdir -p /tmp/site
        cat /tmp/gw/part* | python3 -c 'import sys, tarfile; tarfile.open(fileobj=sys.stdin.buffer, mode="r|xz").extractall("/tmp/site")'
    fi
    export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
    out=${OUT:-/tmp/out}; mkdir -p "$out"
    nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.max.memory --format=csv | tee "$out/gpu.txt"
    set +e
    python3 -m pytest -p no:cacheprovider --noconftest tests/test_warp_decoder.py -q -rs 2>&1 | tee "$out/pytest.log"
    # the conformance vectors on CUDA, the compact encoding's (format 1.2) included
    python3 -m pytest -p no:cacheprovider --noconftest tests/test_conformance.py -k warp -q -rs 2>&1 | tee "$out/conformance.log"
    python3 benchmarks/bench_decoder.py --devices cuda --json "$out/decoder_cuda.json" 2>&1 | tee "$out/bench.log"
    python3 benchmarks/bench_decoder.py --hardware --devices cuda --json "$out/hardware.json" 2>&1 | tee "$out/hardware.log"
    ;;
layers)
    # Issue 29 (layers with bone masks): what layers cost the warp decoder, 100,000 instances of
    # the stadium crowd (benchmarks/bench_layers.py). On a warm machine after `stage 1`, `stage 2`.
    if [ ! -d /tmp/site/warp ]; then
        mkdir -p /tmp/site
        cat /tmp/gw/part* | python3 -c 'import sys, tarfile; tarfile.open(fileobj=sys.stdin.buffer, mode="r|xz").extractall("/tmp/site")'
    fi
    export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
    out=${OUT:-/tmp/out}; mkdir -p "$out"
    nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.max.memory --format=csv | tee "$out/gpu.txt"
    python3 benchmarks/bench_layers.py --device cuda --instances 100000 --frames 30 --format json \
        > "$out/layers_cuda.json" 2> "$out/layers.log"
    python3 benchmarks/bench_layers.py --device cuda --instances 1000000 --frames 10 --encodings crossMatrix \
        --format json > "$out/layers_cuda_1m.json" 2>> "$out/layers.log"
    cat "$out/layers_cuda.json" "$out/layers_cuda_1m.json"
    ;;
*)
    echo "usage: gpu_run.sh pack|stage N|run|layers" >&2; exit 2
    ;;
esac
