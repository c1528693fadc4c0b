#!/usr/bin/env bash
# Run the draw-cost benchmark (benchmarks/draw_cost.py, issue 18) and the warp decoder's CUDA tests on
# the GPU machine of the device tool.
#
# The GPU image has numpy, pytest and matplotlib but no OpenGL loader libraries, no moderngl and no
# warp. So, here, `pack` gathers what the run needs into folders that git ignores:
#   .gl/       the GL loader libraries (libglvnd's libEGL, libOpenGL, ...; Debian .deb files),
#   .whl/      moderngl and glcontext wheels for the image's Python 3.12,
#   .gpuwarp/  warp, in two parts (benchmarks/gpu_run.sh pack: warp's wheel is larger than one call
#              may carry).
# On the machine, `stage 1` / `stage 2` keep the two warp parts in /tmp/gw, and `run` unpacks
# everything and runs the tests and the benchmark. The two calls follow each other while the machine
# is warm (it is given back about 30 s after a call):
#
#   here:        bash benchmarks/draw_run.sh pack
#   device call: carry [".gpuwarp/p1", ".gl", ".whl"]  command: bash benchmarks/draw_run.sh stage 1 && bash benchmarks/draw_run.sh smoke
#   device call: carry [".gpuwarp/p2", ".gl", ".whl"]  command: bash benchmarks/draw_run.sh stage 2 && bash benchmarks/draw_run.sh run
#
# `smoke` (no warp yet) opens the EGL context and runs the GL methods at 1,200 stadium instances
# (smoke.json, smoke.log). `run` writes to $OUT: gpu.txt (nvidia-smi), warp_tests.log (pytest
# tests/test_warp_decoder.py on CUDA), draw_tests.log (tests/test_draw_cost.py on the NVIDIA EGL
# driver), draw.log, draw_cost.json, and the report (draw_report.md) and plot (draw_cost.png) made
# from the JSON (matplotlib is in the GPU image). Kept in benchmarks/results/ with the card as suffix:
# draw_cost_h200.json, draw_cost_h200.png, draw_report_h200.md, draw_warp_tests_cuda_h200.log (the
# full run got an H200). The report again, here:
#   python benchmarks/draw_cost.py report --json benchmarks/results/draw_cost_h200.json --markdown
# `factors` (one call, no warp part needed: carry [".gl", ".whl"]) runs the one-factor study around
# VB's vertex cost (draw_factors.json) and the GL methods of the stadium character again
# (draw_cost_gl.json), both on the card the call got. Kept as draw_factors_<card>.json and
# draw_cost_gl_<card>.json. FACTOR_SIZES=100000,10000,1000000 FACTORS_ONLY=1 runs the study alone.
# DRAW_ARGS adds options to draw_cost.py run (default budget: 320 s of the call's 600).
#
# Issue 25 (the shipped module in both skin bindings, static and VAT beside it): ONE device call, no
# warp (the VB methods need none), after `NO_WARP=1 bash benchmarks/draw_run.sh pack` here:
#   device call: carry [".gl", ".whl"]  command: bash benchmarks/draw_run.sh issue25
# It runs tests/test_draw_cost.py on the NVIDIA EGL driver (draw_tests.log), then
# `draw_cost.py run --plan issue25` (stadium 10,000 / 100,000 / 1,000,000 and dense 1,200 / 10,000
# instances; static, vb, vb_pulled, vat; each read back against numpy first; budget 400 s, killed at
# 470 s: the JSON is rewritten after every configuration) into draw_issue25.json and draw_issue25.log,
# and the report with the factor table into draw_issue25_report.md. `issue25-texture` (same call, same
# carry) runs `--plan issue25-texture`: static, vb, vb_pulled and vb_pulled_texture (the records in an
# RGBA32UI texture, as WebGL 2 reads them) at the same sizes, into draw_issue25_texture*.
#
# Issue 29 (levels of detail: the stadium at 1,000,000 / 100,000 / 10,000 instances seen from the grid's
# edge, one level against three sharing the texture): ONE device call, no warp. The GPU image has no
# meshoptimizer, so the levels are made here first (the same vbusd.baking.lod call) into .lod/:
#   here:        NO_WARP=1 bash benchmarks/draw_run.sh pack && bash benchmarks/draw_run.sh pack-lod
#   device call: carry [".gl", ".whl", ".lod"]  command: bash benchmarks/draw_run.sh issue29
# It writes draw_tests.log, draw_issue29.json, draw_issue29.log and draw_issue29_report.md (the table of
# frame time, GPU time and triangles drawn per crowd size and level count) to $OUT.
#
# Issue 36 (the previous-frame pose's cost: static, vb and vb_pulled_texture, each VB configuration
# without and with `--previous`): ONE device call, no warp, after `NO_WARP=1 bash benchmarks/draw_run.sh pack`:
#   device call: carry [".gl", ".whl"]  command: bash benchmarks/draw_run.sh issue36
# It writes draw_tests.log, draw_issue36.json, draw_issue36.log and draw_issue36_report.md (with the
# previous-pose cost table) to $OUT.
# Issue 37 (crowd variety on vs off, --plan issue37): the same call with `issue37` instead.
set -euo pipefail
cmd=${1:?usage: draw_run.sh pack|pack-lod|stage N|smoke|run|factors|issue25|issue25-texture|issue29|issue36|issue37}
case "$cmd" in
pack)
    exclude="$(git rev-parse --git-dir)/info/exclude"; mkdir -p "$(dirname "$exclude")"
    for ignored in /.gl/ /.whl/; do grep -qx "$ignored" "$exclude" 2>/dev/null || echo "$ignored" >> "$exclude"; done
    mkdir -p .gl .whl /tmp/amd64/partial
    o='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64'
    # shellcheck disable=SC2086
    apt-get $o update -qq
    # shellcheck disable=SC2086
    (cd .gl && apt-get $o download libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2)
    python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
        --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
        --platform manylinux1_x86_64 -d .whl moderngl==5.13.0 glcontext==3.1.0 \
        usd-core OpenEXR pypng pygltflib dataclasses-json marshmallow typing-inspect mypy-extensions deprecated wrapt \
        jsonschema jsonschema-specifications referencing rpds-py attrs typing-extensions click rich markdown-it-py mdurl \
        pygments  # vbusd's core dependencies but numpy (the image has it) and warp: the shaders come from vbusd.shader
    if [ -n "${NO_WARP:-}" ]; then  # issue25 needs no warp
        ls -l .gl .whl
    else
        [ -d .gpuwarp/p2 ] || bash benchmarks/gpu_run.sh pack
        ls -l .gl .whl .gpuwarp/p*
    fi
    ;;
pack-lod)
    exclude="$(git rev-parse --git-dir)/info/exclude"; mkdir -p "$(dirname "$exclude")"
    grep -qx /.lod/ "$exclude" 2>/dev/null || echo /.lod/ >> "$exclude"
    # PYTHON: an interpreter with vbusd and meshoptimizer (pip install -e '.[lod]'), default python3.
    "${PYTHON:-python3}" benchmarks/draw_cost.py lod-meshes --out .lod/stadium_lods.npz
    ;;
stage)
    bash benchmarks/gpu_run.sh stage "$2"
    ;;
smoke|run|factors|issue25|issue25-texture|issue29|issue36|issue37)
    out=${OUT:-/tmp/out}; mkdir -p "$out"
    for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/glsite .whl/*.whl
    if [ "$cmd" = run ] && [ ! -d /tmp/site/warp ]; then
        mkdir -p /tmp/site
        cat /tmp/gw/part* | python3 -c 'import sys, tarfile; tarfile.open(fileobj=sys.stdin.buffer, mode="r|xz").extractall("/tmp/site")'
    fi
    export PYTHONPATH=/tmp/site:/tmp/glsite:$PWD PYTHONUNBUFFERED=1
    egl_check='import moderngl; c = moderngl.create_context(standalone=True, backend="egl", require=430); print(c.info["GL_RENDERER"], c.info["GL_VERSION"])'
    if ! python3 -c "$egl_check"; then
        export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
        python3 -c "$egl_check" || echo "no EGL context: the benchmark will fail" >&2
    fi
    nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.max.sm,clocks.max.memory --format=csv | tee "$out/gpu.txt"
    set +e
    if [ "$cmd" = factors ]; then
        # No warp needed: the one-factor study, then the GL methods of the stadium character (on
        # whatever card this call got, so that the goal's ratios come from one card).
        timeout 60 python3 -m pytest -p no:cacheprovider --noconftest tests/test_draw_cost.py -q -rs 2>&1 | tee "$out/draw_tests.log"
        timeout 300 python3 benchmarks/draw_cost.py factors --json "$out/draw_factors.json" \
            --sizes "${FACTOR_SIZES:-100000,10000}" 2>&1 | tee "$out/factors.log"
        python3 benchmarks/draw_cost.py report --json "$out/draw_factors.json"
        [ -n "${FACTORS_ONLY:-}" ] && exit 0
        timeout 200 python3 benchmarks/draw_cost.py run --json "$out/draw_cost_gl.json" --characters stadium \
            --methods static,vb,vat,palette --budget 170 2>&1 | tee "$out/draw.log"
        python3 benchmarks/draw_cost.py report --json "$out/draw_cost_gl.json" --markdown > "$out/draw_report_gl.md" 2>&1
        tail -12 "$out/draw_report_gl.md"
        exit 0
    fi
    if [ "$cmd" = smoke ]; then
        timeout 90 python3 benchmarks/draw_cost.py run --json "$out/smoke.json" --sizes 1200 --characters stadium \
            --methods static,vb,vb_pulled,vat,palette --budget 60 --per-config-s 0.5 --no-factors 2>&1 | tee "$out/smoke.log"
        exit 0
    fi
    if [ "$cmd" = issue29 ]; then
        export VBUSD_LOD_MESHES=.lod/stadium_lods.npz  # the levels made here by pack-lod (no meshoptimizer there)
        timeout 60 python3 -m pytest -p no:cacheprovider --noconftest tests/test_draw_cost.py -q -rs 2>&1 | tee "$out/draw_tests.log"
        # shellcheck disable=SC2086
        timeout 470 python3 benchmarks/draw_cost.py run --plan issue29 \
            --json "$out/draw_issue29.json" ${DRAW_ARGS:-} 2>&1 | tee "$out/draw_issue29.log"
        timeout 20 python3 benchmarks/draw_cost.py report --json "$out/draw_issue29.json" --markdown \
            > "$out/draw_issue29_report.md" 2>&1
        tail -12 "$out/draw_issue29_report.md"
        exit 0
    fi
    if [ "$cmd" = issue25 ] || [ "$cmd" = issue25-texture ] || [ "$cmd" = issue36 ] || [ "$cmd" = issue37 ]; then
        plan=$cmd; name=${cmd//-/_}
        timeout 60 python3 -m pytest -p no:cacheprovider --noconftest tests/test_draw_cost.py -q -rs 2>&1 | tee "$out/draw_tests.log"
        # shellcheck disable=SC2086
        timeout 470 python3 benchmarks/draw_cost.py run --plan "$plan" --json "$out/draw_$name.json" ${DRAW_ARGS:-} \
            2>&1 | tee "$out/draw_$name.log"
        timeout 20 python3 benchmarks/draw_cost.py report --json "$out/draw_$name.json" --markdown \
            > "$out/draw_${name}_report.md" 2>&1
        tail -20 "$out/draw_${name}_report.md"
        exit 0
    fi
    timeout 100 python3 -m pytest -p no:cacheprovider --noconftest tests/test_warp_decoder.py -q -rs 2>&1 | tee "$out/warp_tests.log"
    timeout 60 python3 -m pytest -p no:cacheprovider --noconftest tests/test_draw_cost.py -q -rs 2>&1 | tee "$out/draw_tests.log"
    # shellcheck disable=SC2086
    timeout 360 python3 benchmarks/draw_cost.py run --json "$out/draw_cost.json" --budget 320 ${DRAW_ARGS:-} 2>&1 | tee "$out/draw.log"
    timeout 40 python3 benchmarks/draw_cost.py report --json "$out/draw_cost.json" --markdown --plot "$out/draw_cost.png" \
        > "$out/draw_report.md" 2>&1
    tail -30 "$out/draw_report.md"
    ;;
*)
    echo "usage: draw_run.sh pack|pack-lod|stage N|smoke|run|factors|issue25|issue25-texture|issue29|issue36|issue37" >&2; exit 2
    ;;
esac
