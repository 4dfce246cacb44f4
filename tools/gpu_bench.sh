#!/bin/bash
# Issue #28's figures on a real GPU (docs/benchmarks.md, "On a real GPU"): the generator's
# stage table (`trainer bench`, wgpu and NdArray), and the training step (`trainer bench-train`,
# NdArray vs wgpu at 128², wgpu at 256² and 512²), all in one run, with the adapter printed.
#
# Run from the repository root of a Linux machine with a GPU and its Vulkan driver, with .gl/
# (ignored by git) holding:
#   trainer.gz  a release trainer: CARGO_PROFILE_RELEASE_STRIP=true cargo build --release -p trainer,
#               then gzip -9 -c target/release/trainer > .gl/trainer.gz
#   *.deb       where the machine lacks the Vulkan loader and GL dispatch libraries (containers):
#               apt-get download libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2
#               (with libvulkan1 alone NVIDIA's ICD gave "no adapter" on the H200 machine; with all seven it worked).
#               They are unpacked into / : do that only on a disposable machine or container.
# Writes its logs to $OUT (default ./gpu_bench_out). Takes 5–8 minutes on an H200.
OUT=${OUT:-gpu_bench_out}
mkdir -p "$OUT"
for f in .gl/*.deb; do [ -f "$f" ] && dpkg -x "$f" /; done; ldconfig
T=/tmp/trainer
gzip -dc .gl/trainer.gz > $T && chmod +x $T || { echo 'no trainer'; exit 1; }
export XDG_RUNTIME_DIR=/tmp
START=$(date +%s)
left() { echo $(( $1 - ($(date +%s) - START) )); }
{ nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv; nproc; uname -r; } 2>&1 | tee $OUT/machine.txt
ls /usr/share/vulkan/icd.d /etc/vulkan/icd.d /usr/local/nvidia/share/vulkan/icd.d 2>&1 | tee -a $OUT/machine.txt
# Find the NVIDIA adapter: the default search first, then the driver's own ICD files.
for icd in "" /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json /usr/share/vulkan/icd.d/nvidia_icd.json /etc/vulkan/icd.d/nvidia_icd.json; do
  if [ -n "$icd" ]; then [ -f "$icd" ] || continue; export VK_DRIVER_FILES=$icd; fi
  VK_LOADER_DEBUG=error timeout 90 $T bench --configs tiny --backend wgpu > $OUT/probe.txt 2>&1
  grep "^wgpu adapter" $OUT/probe.txt | tee -a $OUT/machine.txt
  if grep -q "^wgpu adapter:" $OUT/probe.txt && ! grep -q SOFTWARE $OUT/probe.txt; then break; fi
done
echo "VK_DRIVER_FILES=$VK_DRIVER_FILES" | tee -a $OUT/machine.txt
# 1. Generator stages, wgpu then ndarray (same machine, same run of this script).
timeout $(left 170) $T bench --configs demo,paper --backend wgpu --repeats 2 2>&1 | tee $OUT/bench_wgpu.txt
timeout $(left 230) $T bench --configs demo --backend ndarray 2>&1 | tee $OUT/bench_ndarray.txt
# 2. Training step, NdArray vs wgpu at 128² (the ratio in one run).
timeout $(left 360) $T bench-train --configs demo --backends ndarray,wgpu --res 128 --steps 2 --work /tmp/bt 2>&1 | tee $OUT/bench_train_128.txt
# 3. Training step on the GPU at 256² and 512², demo and paper configs.
timeout $(left 520) $T bench-train --configs demo,paper --backends wgpu --res 256,512 --steps 2 --work /tmp/bt 2>&1 | tee $OUT/bench_train_gpu.txt
echo "script wall $(( $(date +%s) - START )) s" | tee -a $OUT/machine.txt
