// What the e2e, benchmark and soak scripts share: headless Chromium with WebGPU on
// SwiftShader, the app's status and a poll on it, the e2e photo composited over grey, and the
// IoU of the app's photo masks against a truth.

import { chromium } from 'playwright-core';
import { PNG } from 'pngjs';
import fs from 'node:fs';

/// Headless Chromium with WebGPU on SwiftShader (GETAVATAR_CHROMIUM, default /usr/bin/chromium).
export function launchChromium(extraArgs = []) {
  return chromium.launch({
    executablePath: process.env.GETAVATAR_CHROMIUM ?? '/usr/bin/chromium',
    headless: true,
    args: ['--no-sandbox', '--enable-unsafe-webgpu', '--use-angle=swiftshader', '--enable-features=Vulkan',
      '--use-vulkan=swiftshader', '--disable-quic', ...extraArgs],
  });
}

/// `status()`: the app's `window.getavatar.status()` (null before the app is up, or while the
/// page cannot answer); `waitFor(pred, what, timeout, describe)`: poll it every `intervalMs`
/// until `pred` holds, else throw naming `what` (and `describe(lastStatus)` when given).
export function appStatus(page, { intervalMs = 250, timeoutMs = 1800000 } = {}) {
  const status = () => page.evaluate(() => (window.getavatar ? window.getavatar.status() : null)).catch(() => null);
  async function waitFor(pred, what, timeout = timeoutMs, describe = null) {
    const t0 = Date.now();
    for (;;) {
      const s = await status();
      if (s && pred(s)) return s;
      if (Date.now() - t0 > timeout) {
        throw new Error(`timed out waiting for ${what}${describe ? `; status: ${describe(s)}` : ''}`);
      }
      await page.waitForTimeout(intervalMs);
    }
  }
  return { status, waitFor };
}

/// The e2e photo (fixtures/kick_clothed.png) composited over grey 120, as PNG bytes.
export function greyPhoto() {
  const render = PNG.sync.read(fs.readFileSync(new URL('./fixtures/kick_clothed.png', import.meta.url)));
  for (let k = 0; k < render.data.length; k += 4) {
    const a = render.data[k + 3] / 255;
    for (let c = 0; c < 3; c++) render.data[k + c] = Math.round(render.data[k + c] * a + 120 * (1 - a));
    render.data[k + 3] = 255;
  }
  return PNG.sync.write(render);
}

/// The pixel index of a `width` × `height` image at the normalised point (u, v) in [0, 1)².
export const pixelAt = (width, height, u, v) =>
  Math.min(height - 1, Math.floor(v * height)) * width + Math.min(width - 1, Math.floor(u * width));

/// IoU of a mask of `window.getavatar.photoMasks()` (`bits`: '0'/'1' per pixel,
/// `masks.width` × `masks.height`, e.g. `masks.person`) against a truth read at each pixel's
/// centre: `truthAt(u, v)` (normalised photo coordinates) → whether the person is there.
/// 0 when neither has a pixel.
export function maskIou(masks, bits, truthAt) {
  let [both, either] = [0, 0];
  for (let y = 0; y < masks.height; y++) {
    for (let x = 0; x < masks.width; x++) {
      const a = bits[y * masks.width + x] === '1', b = truthAt((x + 0.5) / masks.width, (y + 0.5) / masks.height);
      both += a && b; either += a || b;
    }
  }
  return either ? both / either : 0;
}
