// Khronos glTF-Validator on .glb files: prints each file's counts and its messages, exits 1
// when any file has an error or a warning. Usage: node validate_glb.mjs FILE...
import fs from 'node:fs';
import validator from 'gltf-validator';

let bad = 0;
for (const f of process.argv.slice(2)) {
  const report = await validator.validateBytes(new Uint8Array(fs.readFileSync(f)));
  const { numErrors, numWarnings, numInfos, messages } = report.issues;
  const info = report.info ?? {};
  console.log(`${f}: ${numErrors} errors, ${numWarnings} warnings, ${numInfos} infos; ` +
    `${info.animationCount ?? 0} animations, ${info.totalVertexCount ?? '?'} vertices, skins: ${info.hasSkins ?? false}, textures: ${info.hasTextures ?? false}`);
  for (const m of messages) console.log(`  ${m.severity === 0 ? 'error' : m.severity === 1 ? 'warning' : 'info'} ${m.code} ${m.pointer ?? ''}: ${m.message}`);
  if (numErrors || numWarnings) bad++;
}
process.exit(bad ? 1 : 0);
