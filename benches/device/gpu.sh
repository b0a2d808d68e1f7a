#!/usr/bin/env bash
# Real-GPU figures (issue 11): the GPU tracer's primary rays per second at
# 1920x1080 on terrain 2048² and on the continent's render window, and at
# 3840x2160 on terrain, on a machine with an NVIDIA GPU whose image has the
# driver but no Vulkan loader. Run from the repository root, with:
#   .gl/     the loader's Debian packages, fetched on a machine with apt:
#            (cd .gl && apt-get download libvulkan1 libegl1 libglvnd0 \
#               libopengl0 libgl1 libglx0 libgles2)
#   .devbin/ a stripped release binary (strip -o .devbin/brickworld
#            target/release/brickworld)
# Results (JSON and logs) go to $OUT; README "On a real GPU" has the
# figures of 2026-12-04 and docs/bench/h200/ their files.
set -u
OUT=${OUT:-/tmp/gpu-out}
mkdir -p "$OUT"
for f in .gl/*.deb; do dpkg -x "$f" /; done
ldconfig
icd=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
[ -f "$icd" ] && export VK_DRIVER_FILES=$icd
nvidia-smi --query-gpu=name,driver_version,clocks.sm,clocks.max.sm,clocks.mem --format=csv | tee "$OUT/nvidia-smi.txt"
nproc
export XDG_RUNTIME_DIR=$(mktemp -d)
bw=${BW:-.devbin/brickworld}
set -o pipefail
# Each 1080p run also measures every image's error against a 16-sample CPU
# reference (the device machine's 16 cores: seconds a view) and charts speed
# against it over C; the 2160p run skips the reference (--spp 0). The three
# timeouts stay within one call's 600 s.
timeout 240 "$bw" bench gpu --scene terrain --size 2048x256x2048 --lod 1,2 \
  --json "$OUT/gpu_terrain_1080p.json" --chart "$OUT/gpu_terrain_1080p.svg" \
  2>&1 | tee "$OUT/terrain_1080p.log"
timeout 200 "$bw" bench gpu --world worlds/continent.toml --lod 1,2 \
  --json "$OUT/gpu_continent_1080p.json" --chart "$OUT/gpu_continent_1080p.svg" \
  2>&1 | tee "$OUT/continent_1080p.log"
timeout 150 "$bw" bench gpu --scene terrain --size 2048x256x2048 --lod 1 \
  --width 3840 --height 2160 --frames 10 --spp 0 \
  --json "$OUT/gpu_terrain_2160p.json" 2>&1 | tee "$OUT/terrain_2160p.log"
echo done
