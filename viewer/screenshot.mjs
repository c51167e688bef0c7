// Render the viewer in headless Debian chromium (software WebGL) and save a screenshot.
// usage: node screenshot.mjs URL OUT.png [WIDTH HEIGHT TIMEOUT_MS]; prints a JSON summary on stdout.
import { chromium } from 'playwright-core';

const [url, out, width = '1280', height = '800', timeout = '90000'] = process.argv.slice(2);
const browser = await chromium.launch({
  executablePath: process.env.MS3D_CHROMIUM || '/usr/bin/chromium',
  args: ['--no-sandbox', '--disable-gpu', '--use-angle=swiftshader', '--enable-unsafe-swiftshader',
         '--disable-background-networking', '--no-first-run'],
});
const result = { url, out, ready: false, console: [] };
try {
  const page = await browser.newPage({ viewport: { width: +width, height: +height } });
  page.on('console', (m) => { if (m.type() === 'error' || m.type() === 'warning') result.console.push(`${m.type()}: ${m.text()}`); });
  page.on('pageerror', (e) => result.console.push(`pageerror: ${e.message}`));
  page.on('response', (r) => { if (r.status() >= 400) result.console.push(`http ${r.status()}: ${r.url()}`); });
  await page.goto(url);
  await page.waitForFunction(() => window.ms3d && window.ms3d.ready, null, { timeout: +timeout });
  result.ready = true;
  result.pick = await page.evaluate(() => window.ms3d.pickAt(innerWidth / 2, innerHeight / 2));
  result.state = await page.evaluate(() => ({ models: window.ms3d.models, faces: window.ms3d.faces, errors: window.ms3d.errors, points: window.ms3d.points, before: window.ms3d.before }));
  result.view = await page.evaluate(() => window.ms3d.view && window.ms3d.view());
  result.measure = await page.evaluate(() => window.ms3d.measure);
  await page.screenshot({ path: out });
} catch (e) {
  result.error = String(e);
  try {
    const page = browser.contexts()[0].pages()[0];
    result.state = await page.evaluate(() => window.ms3d && { models: window.ms3d.models, faces: window.ms3d.faces, errors: window.ms3d.errors, ready: window.ms3d.ready });
    await page.screenshot({ path: out });
  } catch (e2) { result.error += ` (and then ${e2})`; }
} finally {
  await browser.close();
}
process.stdout.write(JSON.stringify(result) + '\n');
