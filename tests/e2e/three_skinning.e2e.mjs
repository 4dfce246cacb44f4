// three.js plays the exported animated avatar as the project does, in headless
// Chromium: GLTFLoader loads the .glb, there is one SkinnedMesh with 24 bones named as SMPL,
// and an AnimationMixer playing each clip puts every vertex where the project's own LBS does
// (positions from `trainer export --frames-json`) within 5 mm at 3 frames per clip. The Khronos
// validator passes every file given (0 errors, 0 warnings).
//
// Usage: node three_skinning.e2e.mjs ANIMATED.glb FRAMES.json [OTHER.glb …]
// (run by `cargo xtask test` on files it exports first).
import { chromium } from 'playwright-core';
import validator from 'gltf-validator';
import fs from 'node:fs';
import path from 'node:path';

const [glbPath, framesPath, ...others] = process.argv.slice(2);
const executablePath = process.env.GETAVATAR_CHROMIUM ?? '/usr/bin/chromium';
let failures = 0;
function check(cond, msg) {
  console.log(`${cond ? 'ok  ' : 'FAIL'} ${msg}`);
  if (!cond) failures++;
}

for (const f of [glbPath, ...others]) {
  const r = await validator.validateBytes(new Uint8Array(fs.readFileSync(f)));
  const msgs = r.issues.messages.slice(0, 3).map((m) => `${m.code} ${m.pointer ?? ''}`).join('; ');
  check(r.issues.numErrors === 0 && r.issues.numWarnings === 0,
    `glTF-Validator on ${path.basename(f)}: ${r.issues.numErrors} errors, ${r.issues.numWarnings} warnings (${r.info?.animationCount ?? 0} animations, skins: ${r.info?.hasSkins}) ${msgs}`);
}

const three = path.resolve('node_modules/three');
const files = {
  '/index.html': ['text/html', `<!doctype html><script type="importmap">{"imports":{"three":"/three/build/three.module.js","three/addons/":"/three/examples/jsm/"}}</script><body></body>`],
};
const browser = await chromium.launch({ executablePath, headless: true, args: ['--no-sandbox', '--disable-background-networking', '--no-first-run'] });
try {
  const page = await browser.newPage();
  const errors = [];
  page.on('pageerror', (e) => errors.push(e.message));
  page.on('console', (m) => { if (m.type() === 'error') errors.push(m.text()); });
  await page.route('http://getavatar.test/**', async (route) => {
    const u = new URL(route.request().url());
    if (files[u.pathname]) return route.fulfill({ contentType: files[u.pathname][0], body: files[u.pathname][1] });
    if (u.pathname.startsWith('/three/')) {
      return route.fulfill({ contentType: 'text/javascript', body: fs.readFileSync(path.join(three, u.pathname.slice('/three/'.length))) });
    }
    if (u.pathname === '/avatar.glb') return route.fulfill({ contentType: 'model/gltf-binary', body: fs.readFileSync(glbPath) });
    return route.fulfill({ status: 404, body: 'not found' });
  });
  await page.goto('http://getavatar.test/index.html');
  const expected = JSON.parse(fs.readFileSync(framesPath, 'utf8'));
  const result = await page.evaluate(async (expected) => {
    const THREE = await import('three');
    const { GLTFLoader } = await import('three/addons/loaders/GLTFLoader.js');
    const gltf = await new GLTFLoader().loadAsync('/avatar.glb');
    const skinned = [];
    gltf.scene.traverse((o) => { if (o.isSkinnedMesh) skinned.push(o); });
    const out = { skinned: skinned.length, bones: [], clips: [] };
    if (skinned.length !== 1) return out;
    const mesh = skinned[0];
    out.bones = mesh.skeleton.bones.map((b) => b.name);
    const mixer = new THREE.AnimationMixer(gltf.scene);
    const v = new THREE.Vector3();
    for (const c of expected.clips) {
      const clip = gltf.animations.find((a) => a.name === c.name);
      if (!clip) { out.clips.push({ name: c.name, missing: true }); continue; }
      mixer.stopAllAction();
      const action = mixer.clipAction(clip);
      action.setLoop(THREE.LoopOnce, 1);
      action.clampWhenFinished = true;
      action.play();
      for (const f of c.frames) {
        mixer.setTime(f.time);
        gltf.scene.updateMatrixWorld(true);
        mesh.skeleton.update();
        let worst = 0;
        const n = mesh.geometry.attributes.position.count;
        for (let i = 0; i < n; i++) {
          mesh.getVertexPosition(i, v);
          v.applyMatrix4(mesh.matrixWorld);
          const d = Math.hypot(v.x - f.positions[3 * i], v.y - f.positions[3 * i + 1], v.z - f.positions[3 * i + 2]);
          worst = Math.max(worst, d);
        }
        out.clips.push({ name: c.name, frame: f.frame, worst, n, expectedN: f.positions.length / 3 });
      }
      action.stop();
    }
    return out;
  }, expected);
  const smpl = ['pelvis', 'left_hip', 'right_hip', 'spine1', 'left_knee', 'right_knee', 'spine2', 'left_ankle', 'right_ankle', 'spine3',
    'left_foot', 'right_foot', 'neck', 'left_collar', 'right_collar', 'head', 'left_shoulder', 'right_shoulder', 'left_elbow',
    'right_elbow', 'left_wrist', 'right_wrist', 'left_hand', 'right_hand'];
  check(result.skinned === 1, `three.js GLTFLoader finds one SkinnedMesh (${result.skinned})`);
  check(result.bones.length === 24 && result.bones.every((b, i) => b === smpl[i]), `24 bones named as SMPL (${result.bones.length}: ${result.bones.slice(0, 4).join(', ')}, …)`);
  for (const c of result.clips) {
    if (c.missing) { check(false, `clip ${c.name} is in the file`); continue; }
    check(c.n === c.expectedN && c.worst <= 0.005,
      `AnimationMixer, clip ${c.name} frame ${c.frame}: ${c.n} vertices within ${(1000 * c.worst).toFixed(2)} mm of the project's LBS (≤ 5 mm)`);
  }
  check(result.clips.length >= 3, `${result.clips.length} clip frames checked`);
  check(errors.length === 0, `no page errors (${errors.slice(0, 2).join(' | ')})`);
} catch (e) {
  console.log(`FAIL ${e.stack ?? e}`);
  failures++;
} finally {
  await browser.close();
}
console.log(failures ? `three.js skinning: ${failures} check(s) failed` : 'three.js skinning: all checks passed');
process.exit(failures ? 1 : 0);
