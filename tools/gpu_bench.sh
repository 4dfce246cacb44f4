#!/bin/bash
# The figures on a real GPU (docs/benchmarks.md, "On a real GPU"): the generator's
# stage table (`trainer bench generator`, wgpu and NdArray), and the training step (`trainer bench train`,
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
# Writes its logs to $OUT (default ./gpu_bench_out), and, with PACK=file.tgz, packs $OUT into that
# one file after each part (a device machine returns few files). The default parts take 5–8
# minutes on an H200.
OUT=${OUT:-gpu_bench_out}
mkdir -p "$OUT"
pack() { if [ -n "$PACK" ]; then tar czf "$PACK.tmp" -C "$OUT" . && mv "$PACK.tmp" "$PACK"; fi; }
for f in .gl/*.deb; do [ -f "$f" ] && dpkg -x "$f" /; done; ldconfig
T=/tmp/trainer
gzip -dc .gl/trainer.gz > $T && chmod +x $T || { echo 'no trainer'; exit 1; }
export XDG_RUNTIME_DIR=/tmp
START=$(date +%s)
{ nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv; nproc; uname -r; } 2>&1 | tee $OUT/machine.txt
ls /usr/share/vulkan/icd.d /etc/vulkan/icd.d /usr/local/nvidia/share/vulkan/icd.d 2>&1 | tee -a $OUT/machine.txt
# Find the NVIDIA adapter: the default search first, then the driver's own ICD files.
for icd in "" /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json /usr/share/vulkan/icd.d/nvidia_icd.json /etc/vulkan/icd.d/nvidia_icd.json; do
  if [ -n "$icd" ]; then [ -f "$icd" ] || continue; export VK_DRIVER_FILES=$icd; fi
  VK_LOADER_DEBUG=error timeout 90 $T bench generator --configs tiny --backend wgpu > $OUT/probe.txt 2>&1
  grep "^wgpu adapter" $OUT/probe.txt | tee -a $OUT/machine.txt
  if grep -q "^wgpu adapter:" $OUT/probe.txt && ! grep -q SOFTWARE $OUT/probe.txt; then break; fi
done
echo "VK_DRIVER_FILES=$VK_DRIVER_FILES" | tee -a $OUT/machine.txt
# PARTS picks what runs (default: stages,train128,traingpu); each command has its own time limit.
#   stages    generator stage tables, wgpu (demo, paper) then NdArray (demo); each table is
#             printed twice: pipelined (the app's way) and synced at each stage's end
#   train128  training step, NdArray vs wgpu at 128² (the ratio in one run)
#   traingpu  training step on the GPU at 256² and 512², demo and paper configs
#   paper512  the paper config at 512² alone, batch 1 (its batch-2 step crashed inside NVIDIA's
#             driver once), with the kernel log's tail whatever happens
#   photo     `trainer invert --preset instant` on NdArray and wgpu, two processes each (the
#             first avatar's time), the same on a photo end to end where PHOTO names one (the
#             prefix of PHOTO.png, .kp.json, .mask.png and its fit PHOTO.fit.json), and a short
#             `fast` on wgpu for the seconds per W+ and PTI step; DATA (default data/heldout512:
#             `synth-scans --count 3 --seed 1`, `prepare --views 4 --res 512 --seed 1 --limit 3`)
#             and its entry ENTRY (default 0001/000.png)
#   video     `trainer motion-from-video` on the dance fixture's keypoints, NdArray and wgpu
#   encoder   encoder pairs rendered by RENDER_PROCS (default 14) wgpu processes for RENDER_S
#             seconds (`train-encoder --render-part k/N`, seed 7), then the shipped encoder
#             trained further on the contiguous shards that were done, on wgpu, for TRAIN_S
#             seconds (batch 32, lr 0.001); its log, snapshots and best weights into $OUT/encoder
#   compare   .gl/trainer_b.gz (another build, e.g. another burn feature set) against
#             .gl/trainer.gz, alternating (ROUNDS, default 2): stage tables and the wgpu
#             training step at 128²
PARTS=${PARTS:-stages,train128,traingpu}
has() { [[ ",$PARTS," == *",$1,"* ]]; }
if has stages; then
  timeout 170 $T bench generator --configs demo,paper --backend wgpu --repeats 2 2>&1 | tee $OUT/bench_wgpu.txt
  timeout 60 $T bench generator --configs demo --backend ndarray 2>&1 | tee $OUT/bench_ndarray.txt
fi
has train128 && timeout 130 $T bench train --configs demo --backends ndarray,wgpu --res 128 --steps 2 --work /tmp/bt 2>&1 | tee $OUT/bench_train_128.txt
has traingpu && timeout 160 $T bench train --configs demo,paper --backends wgpu --res 256,512 --steps 2 --work /tmp/bt 2>&1 | tee $OUT/bench_train_gpu.txt
if has compare; then
  B=/tmp/trainer_b
  gzip -dc .gl/trainer_b.gz > $B && chmod +x $B || { echo 'no .gl/trainer_b.gz'; exit 1; }
  for round in $(seq ${ROUNDS:-2}); do
    for t in $T $B; do
      tag=$(basename $t)_$round
      timeout 120 $t bench generator --configs demo,paper --backend wgpu > $OUT/compare_bench_$tag.txt 2>&1
      timeout 100 $t bench train --configs demo --backends wgpu --res 128 --steps 2 --work /tmp/bt > $OUT/compare_train_$tag.txt 2>&1
      tail -3 $OUT/compare_train_$tag.txt
    done
  done
fi
pack
if has photo; then
  # Each backend twice: the first process compiles its kernels (wgpu), fills the drivers'
  # caches and keeps the body context on disk, the second is what a user sees from then on.
  export GETAVATAR_CACHE=/tmp/getavatar-cache
  D=${DATA:-data/heldout512}; E=${ENTRY:-0001/000.png}
  for be in ndarray wgpu; do
    for run in 1 2; do
      timeout 90 $T invert --data $D --entry $E --res 128 --preset instant --texture-res 256 \
        --backend $be --out /tmp/inv_instant_${be}_$run > $OUT/invert_instant_${be}_$run.txt 2>&1
      cp /tmp/inv_instant_${be}_$run/metrics.json $OUT/invert_instant_${be}_$run.json
      grep -E "body context|loaded|start:|first avatar|wrote" $OUT/invert_instant_${be}_$run.txt
    done
  done
  # End to end (PHOTO=prefix of PREFIX.png, .kp.json, .mask.png and the fit PREFIX.fit.json).
  if [ -n "$PHOTO" ]; then
    for be in ndarray wgpu; do
      timeout 90 $T invert --image $PHOTO.png --fit $PHOTO.fit.json --mask $PHOTO.mask.png --keypoints $PHOTO.kp.json \
        --res 128 --preset instant --texture-res 256 --backend $be --out /tmp/inv_photo_$be > $OUT/invert_photo_$be.txt 2>&1
      cp /tmp/inv_photo_$be/metrics.json $OUT/invert_photo_$be.json
      grep -E "loaded|start:|first avatar|wrote" $OUT/invert_photo_$be.txt
    done
  fi
  timeout 120 $T invert --data $D --entry $E --res 128 --preset fast --steps 10 --pti-steps 10 \
    --texture-res 256 --backend wgpu --out /tmp/inv_fast_wgpu > $OUT/invert_fast10_wgpu.txt 2>&1
  cp /tmp/inv_fast_wgpu/metrics.json $OUT/invert_fast10_wgpu.json
  tail -4 $OUT/invert_fast10_wgpu.txt
  pack
fi
if has video; then
  for be in ndarray wgpu; do
    timeout 90 $T motion-from-video --keypoints tests/fixtures/video/dance.keypoints.jsonl --backend $be \
      --out /tmp/dance_$be.npz 2>&1 | tail -3 | tee $OUT/video_$be.txt
  done
  pack
fi
if has encoder; then
  E=/tmp/enc; NP=${RENDER_PROCS:-14}
  mkdir -p $E $OUT/encoder
  for k in $(seq 0 $((NP - 1))); do
    RAYON_NUM_THREADS=1 timeout ${RENDER_S:-180} $T train-encoder --pairs 64000 --seed 7 --render-part $k/$NP \
      --backend wgpu --out $E > /tmp/render_$k.log 2>&1 &
  done
  wait
  tail -2 /tmp/render_0.log > $OUT/encoder/render_0.txt
  # The contiguous shards from 0 that were done (a shard counts once its codes are on disk).
  n=0; while [ -f $E/pairs/$(printf shard_%04d $n).safetensors ]; do n=$((n + 1)); done
  echo "encoder pairs: $n contiguous shards of 64 ($(ls $E/pairs/*.safetensors | wc -l) done) in ${RENDER_S:-180} s by $NP processes" | tee $OUT/encoder/pairs.txt
  if [ $n -ge 2 ]; then
    E2=/tmp/enc_train; mkdir -p $E2/pairs
    for i in $(seq 0 $((n - 1))); do mv $E/pairs/$(printf shard_%04d $i).* $E2/pairs/; done
    t_train=$(date +%s)
    for be in wgpu ndarray; do
      left=$(( ${TRAIN_S:-180} - ($(date +%s) - t_train) ))
      [ $left -gt 20 ] || break
      timeout $left $T train-encoder --pairs $((64 * n)) --seed 7 --steps 100000 --batch 32 --lr 0.001 \
        --snapshot-every 50 --init assets/models/encoder.safetensors --backend $be --out $E2 > $OUT/encoder/train_$be.txt 2>&1
      rc=$?; echo "train-encoder on $be: exit $rc" | tee -a $OUT/encoder/pairs.txt
      [ $rc -eq 124 ] || [ $rc -eq 0 ] && break   # ran to its time: done; an early failure: the CPU next
    done
    cp $E2/log.jsonl $E2/encoder_best.safetensors $OUT/encoder/
    ls $E2/snapshots | tail -2 | while read f; do cp $E2/snapshots/$f $OUT/encoder/; done
    tail -3 $E2/log.jsonl
  fi
  pack
fi
if has paper512; then
  timeout 200 $T bench train --configs paper --backends wgpu --res 512 --batch 1 --steps 1 --work /tmp/bt 2>&1 | tee $OUT/bench_train_paper512.txt
  echo "exit ${PIPESTATUS[0]}" | tee -a $OUT/bench_train_paper512.txt
  dmesg 2>&1 | tail -20 > $OUT/dmesg_tail.txt
fi
echo "script wall $(( $(date +%s) - START )) s" | tee -a $OUT/machine.txt
pack
