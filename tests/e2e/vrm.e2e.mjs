// VRM 1.0 export as avatar apps read it, in headless Chromium: `@pixiv/three-vrm` loads the
// .vrm (GLTFLoader + VRMLoaderPlugin), finds every required humanoid bone with VRM's parent
// chain, left bones on the avatar's left (+x; it faces +z: the toes are in front of the
// ankles), its normalized humanoid rig in the rest T-pose within 1 cm of the project's rest
// joints, soles at y = 0; `@pixiv/three-vrm-animation` plays the .vrma on that VRM and puts
// the hands and feet within 3 cm of the project's own forward kinematics at the sampled
// frames. The Khronos validator passes every file given with 0 errors.
//
// Usage: node vrm.e2e.mjs AVATAR.vrm AVATAR.joints.json CLIP.vrma CLIP.frames.json [OTHER.vrm|.vrma …]
// (run by `cargo xtask test` on files `trainer export --format vrm|vrma --frames-json` wrote).
import { chromium } from 'playwright-core';
import validator from 'gltf-validator';
import fs from 'node:fs';
import path from 'node:path';

const [vrmPath, jointsPath, vrmaPath, framesPath, ...others] = process.argv.slice(2);
if (!framesPath) {
  console.log('usage: node vrm.e2e.mjs AVATAR.vrm AVATAR.joints.json CLIP.vrma CLIP.frames.json [OTHER …]');
  process.exit(2);
}
const executablePath = process.env.GETAVATAR_CHROMIUM ?? '/usr/bin/chromium';
let failures = 0;
function check(cond, msg) {
  console.log(`${cond ? 'ok  ' : 'FAIL'} ${msg}`);
  if (!cond) failures++;
}

for (const f of [vrmPath, vrmaPath, ...others]) {
  const r = await validator.validateBytes(new Uint8Array(fs.readFileSync(f)));
  const msgs = r.issues.messages.slice(0, 4).map((m) => `${m.code} ${m.pointer ?? ''}`).join('; ');
  check(r.issues.numErrors === 0,
    `glTF-Validator on ${path.basename(f)}: ${r.issues.numErrors} errors, ${r.issues.numWarnings} warnings, ${r.issues.numInfos} infos (extensions: ${r.info?.extensionsUsed?.join(', ')}) ${msgs}`);
}

const mod = (p) => path.resolve('node_modules', p);
const scripts = {
  '/three/': mod('three'),
  '/three-vrm.js': mod('@pixiv/three-vrm/lib/three-vrm.module.js'),
  '/three-vrm-animation.js': mod('@pixiv/three-vrm-animation/lib/three-vrm-animation.module.js'),
};
const html = `<!doctype html><script type="importmap">{"imports":{"three":"/three/build/three.module.js","three/addons/":"/three/examples/jsm/","@pixiv/three-vrm":"/three-vrm.js","@pixiv/three-vrm-animation":"/three-vrm-animation.js"}}</script><body></body>`;
const browser = await chromium.launch({ executablePath, headless: true, args: ['--no-sandbox', '--disable-background-networking', '--no-first-run'] });
try {
  const page = await browser.newPage();
  const errors = [];
  page.on('pageerror', (e) => errors.push(e.message));
  page.on('console', (m) => { if (m.type() === 'error' || m.type() === 'warning') errors.push(`${m.type()}: ${m.text()}`); });
  await page.route('http://getavatar.test/**', async (route) => {
    const u = new URL(route.request().url());
    if (u.pathname === '/index.html') return route.fulfill({ contentType: 'text/html', body: html });
    if (u.pathname.startsWith('/three/')) {
      return route.fulfill({ contentType: 'text/javascript', body: fs.readFileSync(path.join(scripts['/three/'], u.pathname.slice('/three/'.length))) });
    }
    if (scripts[u.pathname]) return route.fulfill({ contentType: 'text/javascript', body: fs.readFileSync(scripts[u.pathname]) });
    if (u.pathname === '/avatar.vrm') return route.fulfill({ contentType: 'model/gltf-binary', body: fs.readFileSync(vrmPath) });
    if (u.pathname === '/clip.vrma') return route.fulfill({ contentType: 'model/gltf-binary', body: fs.readFileSync(vrmaPath) });
    return route.fulfill({ status: 404, body: 'not found' });
  });
  await page.goto('http://getavatar.test/index.html');
  // The project's LBS of the avatar in its .vrm's frame: the .vrma's joints moved from the
  // animation skeleton's floor offset (the body's soles) to the avatar's (its lowest vertex).
  const rest = JSON.parse(fs.readFileSync(jointsPath, 'utf8'));
  const frames = JSON.parse(fs.readFileSync(framesPath, 'utf8'));
  const shift = rest.offset.map((o, i) => o - frames.offset[i]);
  const clip = frames.clips[0];
  for (const f of clip.frames) {
    for (const p of Object.values(f.joints)) for (let i = 0; i < 3; i++) p[i] += shift[i];
  }
  const expected = { rest: rest.joints, clip };
  console.log(`the avatar's floor is ${(shift[1] * 1000).toFixed(1)} mm below the body's soles`);
  const r = await page.evaluate(async (expected) => {
    const THREE = await import('three');
    const { GLTFLoader } = await import('three/addons/loaders/GLTFLoader.js');
    const { VRMLoaderPlugin, VRMHumanBoneParentMap } = await import('@pixiv/three-vrm');
    const { VRMAnimationLoaderPlugin, VRMLookAtQuaternionProxy, createVRMAnimationClip } = await import('@pixiv/three-vrm-animation');
    const loader = new GLTFLoader();
    loader.register((parser) => new VRMLoaderPlugin(parser));
    const animLoader = new GLTFLoader();
    animLoader.register((parser) => new VRMAnimationLoaderPlugin(parser));
    const vrm = (await loader.loadAsync('/avatar.vrm')).userData.vrm;
    const out = { loaded: !!vrm };
    if (!vrm) return out;
    out.meta = { version: vrm.meta.metaVersion, name: vrm.meta.name, permission: vrm.meta.avatarPermission, licence: vrm.meta.licenseUrl };
    const required = ['hips', 'spine', 'head', 'leftUpperLeg', 'leftLowerLeg', 'leftFoot', 'rightUpperLeg', 'rightLowerLeg',
      'rightFoot', 'leftUpperArm', 'leftLowerArm', 'leftHand', 'rightUpperArm', 'rightLowerArm', 'rightHand'];
    out.missing = required.filter((b) => !vrm.humanoid.getRawBoneNode(b));
    // Each bone's nearest humanoid ancestor is the one VRM's spec names (skipping optional
    // bones the file leaves out, as VRM allows).
    const rawToName = new Map();
    for (const name of Object.keys(VRMHumanBoneParentMap)) {
      const n = vrm.humanoid.getRawBoneNode(name);
      if (n) rawToName.set(n, name);
    }
    out.bones = rawToName.size;
    out.badParents = [];
    for (const [node, name] of rawToName) {
      let want = VRMHumanBoneParentMap[name];
      while (want && !vrm.humanoid.getRawBoneNode(want)) want = VRMHumanBoneParentMap[want];
      let p = node.parent;
      while (p && !rawToName.has(p)) p = p.parent;
      const got = p ? rawToName.get(p) : null;
      if (got !== (want ?? null)) out.badParents.push(`${name}: ${got} (want ${want})`);
    }
    vrm.scene.updateMatrixWorld(true);
    const v = new THREE.Vector3();
    const world = (name, normalized) => {
      const n = normalized ? vrm.humanoid.getNormalizedBoneNode(name) : vrm.humanoid.getRawBoneNode(name);
      return n ? n.getWorldPosition(v).toArray() : null;
    };
    const dist = (a, b) => Math.hypot(a[0] - b[0], a[1] - b[1], a[2] - b[2]);
    out.restWorst = 0;
    out.restWorstBone = '';
    for (const [name, p] of Object.entries(expected.rest)) {
      const w = world(name, true);
      const d = w ? dist(w, p) : Infinity;
      if (d > out.restWorst) { out.restWorst = d; out.restWorstBone = name; }
    }
    out.leftUpperArm = world('leftUpperArm', true);
    out.rightUpperArm = world('rightUpperArm', true);
    out.leftFoot = world('leftFoot', false);
    out.leftToes = world('leftToes', false);
    // Soles: the skinned mesh's lowest vertex at rest.
    let lowest = Infinity;
    vrm.scene.traverse((o) => {
      if (!o.isSkinnedMesh) return;
      const n = o.geometry.attributes.position.count;
      for (let i = 0; i < n; i++) {
        o.getVertexPosition(i, v);
        v.applyMatrix4(o.matrixWorld);
        lowest = Math.min(lowest, v.y);
      }
    });
    out.lowest = lowest;
    // The .vrma on this VRM.
    const anim = (await animLoader.loadAsync('/clip.vrma')).userData.vrmAnimations?.[0];
    out.animation = !!anim;
    if (!anim) return out;
    // The look-at's proxy, as three-vrm's animation example sets it up (else it warns).
    if (vrm.lookAt) {
      const proxy = new VRMLookAtQuaternionProxy(vrm.lookAt);
      proxy.name = 'lookAtQuaternionProxy';
      vrm.scene.add(proxy);
    }
    const clip = createVRMAnimationClip(anim, vrm);
    const mixer = new THREE.AnimationMixer(vrm.scene);
    const action = mixer.clipAction(clip);
    action.setLoop(THREE.LoopOnce, 1);
    action.clampWhenFinished = true;
    action.play();
    out.frames = [];
    for (const f of expected.clip.frames) {
      mixer.setTime(f.time);
      vrm.update(0);
      vrm.scene.updateMatrixWorld(true);
      const errs = {};
      let all = 0;
      for (const [name, p] of Object.entries(f.joints)) {
        const w = world(name, false);
        const d = w ? dist(w, p) : Infinity;
        if (['leftHand', 'rightHand', 'leftFoot', 'rightFoot'].includes(name)) errs[name] = d;
        all = Math.max(all, d);
      }
      out.frames.push({ time: f.time, errs, all });
    }
    return out;
  }, expected);

  check(r.loaded && r.meta?.version === '1', `three-vrm loads ${path.basename(vrmPath)} as VRM ${r.meta?.version} ("${r.meta?.name}", avatarPermission ${r.meta?.permission}, ${r.meta?.licence})`);
  check(r.missing?.length === 0, `every required humanoid bone is there (${r.bones} bones mapped; missing: ${r.missing?.join(', ') || 'none'})`);
  check(r.badParents?.length === 0, `each bone's parent is VRM's (${r.badParents?.join('; ') || 'all match'})`);
  check(r.restWorst <= 0.01, `normalized rig in T-pose vs the project's rest joints: worst ${(r.restWorst * 1000).toFixed(2)} mm (${r.restWorstBone})`);
  check(r.leftUpperArm?.[0] > 0.05 && r.rightUpperArm?.[0] < -0.05,
    `leftUpperArm on the avatar's left (+x: ${r.leftUpperArm?.[0].toFixed(3)} m), rightUpperArm on its right (${r.rightUpperArm?.[0].toFixed(3)} m)`);
  check(r.leftToes?.[2] > r.leftFoot?.[2] + 0.05, `the avatar faces +z: toes ${((r.leftToes?.[2] - r.leftFoot?.[2]) * 100).toFixed(1)} cm in front of the ankle`);
  check(Math.abs(r.lowest) < 0.005, `soles at y = 0 (lowest vertex ${(r.lowest * 1000).toFixed(2)} mm)`);
  check(r.animation, `three-vrm-animation loads ${path.basename(vrmaPath)}`);
  for (const f of r.frames ?? []) {
    const worst = Math.max(...Object.values(f.errs));
    check(worst <= 0.03, `.vrma at ${f.time.toFixed(2)} s: hands and feet vs the project's FK: ${Object.entries(f.errs).map(([k, d]) => `${k} ${(d * 1000).toFixed(1)}`).join(', ')} mm (all bones: worst ${(f.all * 1000).toFixed(1)} mm)`);
  }
  check((r.frames?.length ?? 0) >= 3, `${r.frames?.length} sampled times`);
  check(errors.length === 0, `no console errors or warnings (${errors.slice(0, 3).join(' | ')})`);
} catch (e) {
  console.log(`FAIL ${e.stack ?? e}`);
  failures++;
} finally {
  await browser.close();
}
console.log(failures ? `VRM e2e: ${failures} check(s) failed` : 'VRM e2e: all checks passed');
process.exit(failures ? 1 : 0);
