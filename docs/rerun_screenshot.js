// Screenshot of the Rerun web viewer, for docs/figures/rerun-web.png (docs/recordings.md).
//
//   .venv/bin/adnmesh up configs/simbench.yaml --out /tmp/ref.mcap
//   .venv/bin/adnmesh replay /tmp/ref.mcap --web --web-port 9095 &   # prints the URL; kill %1 after
//                                          # (SIGTERM: a background job of a script ignores SIGINT)
//   npm install playwright-core            # in a scratch directory; Debian's chromium package
//   NODE_PATH=<scratch>/node_modules node docs/rerun_screenshot.js \
//        "http://127.0.0.1:9095/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A<grpc port>%2Fproxy" \
//        docs/figures/rerun-web.png 60000
//
// The first argument is the URL replay prints. The viewer renders with the software rasterizer
// in headless Chromium; it fits the plots' axes to the data once it has loaded, so the page is
// given the third argument (ms, default 60 s) first. The picture is taken through the DevTools
// protocol, which does not wait for the page to settle (the viewer redraws continuously).
const fs = require('fs');
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
  await page.waitForTimeout(parseInt(wait || '60000', 10));
  const session = await page.context().newCDPSession(page);
  const { data } = await session.send('Page.captureScreenshot', { format: 'png' });
  fs.writeFileSync(out, Buffer.from(data, 'base64'));
  await browser.close();
})();
