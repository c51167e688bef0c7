// Drive the labelling mode in headless Debian chromium: label two patches, one by a real mouse click (the
// default brush, bad), one good through the same handler at a far screen point in another patch; print what
// the page saw as JSON.
// usage: node label.mjs URL [WIDTH HEIGHT TIMEOUT_MS [click|propose]]   (URL: a `ms3d view --label` page)
// propose: press "next least-sure", label it bad with key b, then the next one good with key g.
import { chromium } from 'playwright-core';

const [url, width = '1024', height = '700', timeout = '90000', mode = 'click'] = process.argv.slice(2);
const browser = await chromium.launch({
  executablePath: process.env.MS3D_CHROMIUM || '/usr/bin/chromium',
  args: ['--no-sandbox', '--disable-gpu', '--use-angle=swiftshader', '--enable-unsafe-swiftshader',
         '--disable-background-networking', '--no-first-run'],
});
const result = { url, ready: false, console: [], clicks: [] };
try {
  const page = await browser.newPage({ viewport: { width: +width, height: +height } });
  // a missing optional MLS points overlay is a 404 the page expects (it probes with HEAD); anything else counts
  page.on('console', (m) => { if (m.type() === 'error' && !m.text().startsWith('Failed to load resource')) result.console.push(`${m.type()}: ${m.text()}`); });
  page.on('response', (r) => { if (r.status() >= 400 && !r.url().endsWith('/points/tileset.json')) result.console.push(`http ${r.status()}: ${r.url()}`); });
  page.on('pageerror', (e) => result.console.push(`pageerror: ${e.message}`));
  await page.goto(url);
  await page.waitForFunction(() => window.ms3d && window.ms3d.ready && window.ms3d.label, null, { timeout: +timeout });
  result.ready = true;
  if (mode === 'propose') {  // the UI path: "next least-sure", then key b labels it bad and moves on
    await page.click('#lnext');
    await page.waitForFunction(() => window.ms3d.label.selected, null, { timeout: 20000 });
    result.proposals = await page.evaluate(() => window.ms3d.label.proposals.slice(0, 3));
    await page.keyboard.press('b');
    await page.waitForFunction(() => window.ms3d.label.labelled.length >= 1, null, { timeout: 20000 });
    await page.keyboard.press('g');
    await page.waitForFunction(() => window.ms3d.label.labelled.length >= 2, null, { timeout: 20000 });
    result.clicks = await page.evaluate(() => window.ms3d.label.labelled);
  } else {
    // screen points below the panel that hit geometry, spread over the view
    const hits = await page.evaluate(() => {
      const out = [];
      for (let y = 0.9; y > 0.35; y -= 0.05) {
        for (let x = 0.1; x < 0.95; x += 0.05) {
          const px = Math.round(x * innerWidth); const py = Math.round(y * innerHeight);
          if (window.ms3d.label.faceCentroidAt(px, py)) out.push([px, py]);
        }
      }
      return out;
    });
    result.n_hits = hits.length;
    const waitIdle = () => page.waitForFunction(() => window.ms3d.label.busy === 0, null, { timeout: 20000 });
    // 1: a real click with the default brush (bad)
    const [x1, y1] = hits[0];
    await page.mouse.click(x1, y1);
    await page.waitForFunction(() => window.ms3d.label.labelled.length >= 1, null, { timeout: 20000 });
    await waitIdle();
    result.clicks.push(await page.evaluate(() => window.ms3d.label.labelled.at(-1)));
    // 2: the farthest hit that lies in another patch, labelled good through the same handler
    for (const [x, y] of hits.slice().reverse()) {
      const other = await page.evaluate(async ([px, py]) => {
        const L = window.ms3d.label; const a = L.labelled.at(-1);
        const r = await fetch('/api/locate', { method: 'POST', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify({ ecef: L.faceCentroidAt(px, py) }) });
        const p = await r.json();
        return p.i !== a.i || p.j !== a.j || p.k !== a.k;
      }, [x, y]);
      if (!other) continue;
      await page.evaluate(([px, py]) => window.ms3d.label.labelAt(px, py, 0), [x, y]);
      await waitIdle();
      result.clicks.push(await page.evaluate(() => window.ms3d.label.labelled.at(-1)));
      break;
    }
  }
  result.state = await page.evaluate(() => ({ labelled: window.ms3d.label.labelled, errors: window.ms3d.label.errors,
                                              panel: document.getElementById('lcount').textContent }));
  if (process.env.MS3D_SHOT) await page.screenshot({ path: process.env.MS3D_SHOT });
} catch (e) {
  result.error = String(e);
} finally {
  await browser.close();
}
process.stdout.write(JSON.stringify(result) + '\n');
