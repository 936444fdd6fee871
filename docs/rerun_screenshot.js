// Screenshot of the Rerun web viewer, for docs/figures/rerun-web.png (README, "Rerun layout").
//
//   .venv/bin/adnmesh up configs/examples/runtime-step.yaml --out /tmp/rs.mcap
//   .venv/bin/adnmesh replay /tmp/rs.mcap --web --web-port 9095 &      # Ctrl-C / kill -INT after
//   npm install playwright-core            # in a scratch directory; Debian's chromium package
//   node docs/rerun_screenshot.js "http://127.0.0.1:9095/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A9876%2Fproxy" \
//        docs/figures/rerun-web.png 25000
//
// The viewer renders with the software rasterizer in headless Chromium; it fits the plots' axes
// to the data once it has loaded, so the page is given 25 s (third argument, ms) first.
const { chromium } = require('playwright-core');

(async () => {
  const [url, out, wait] = process.argv.slice(2);
  const browser = await chromium.launch({
    executablePath: '/usr/bin/chromium',
    args: ['--no-sandbox', '--disable-quic', '--no-first-run', '--disable-background-networking',
           '--disable-component-update', '--disable-sync', '--use-gl=swiftshader',
           '--enable-unsafe-swiftshader'],
  });
  const page = await browser.newPage({ viewport: { width: 1600, height: 1000 } });
  await page.goto(url);
  await page.waitForTimeout(parseInt(wait || '25000', 10));
  await page.screenshot({ path: out });
  await browser.close();
})();
