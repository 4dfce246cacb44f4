// What the benchmark and soak scripts share: headless Chromium with WebGPU on SwiftShader,
// the app's status and a poll on it, and the e2e photo composited over grey.

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
