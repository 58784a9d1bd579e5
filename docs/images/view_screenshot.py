"""The README's screenshot of `ssg view`: the parse of scene env_1641947949113, its object with
the least likely rule on its path clicked, in headless Chromium."""

import sys

from playwright.sync_api import sync_playwright

ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
page_file, scene, out = sys.argv[1:4]
with sync_playwright() as p:
    b = p.chromium.launch(executable_path="/usr/bin/chromium", args=ARGS)
    pg = b.new_page(viewport={"width": 1200, "height": 640})
    pg.goto("file://" + page_file)
    pg.wait_for_function("window.ssgView && window.ssgView.ready")
    names = pg.evaluate(
        "JSON.parse(document.getElementById('ssg-data').textContent).scenes.map(s => s.name)"
    )
    pg.evaluate(f"ssgView.go({names.index(scene)})")
    k = pg.evaluate("""(() => {
      const all = JSON.parse(document.getElementById('ssg-data').textContent);
      const d = all.scenes[ssgView.state.scene];
      let best = -1, low = Infinity;
      d.objects.forEach((n, k) => {
        let m = Infinity;
        for (let j = n; j >= 0; j = d.nodes[j].parent) m = Math.min(m, Number(d.nodes[j].log_prob));
        if (m < low) { low = m; best = k; }
      });
      return best; })()""")
    x, y = pg.evaluate(f"ssgView.screenPoint({k})")
    box = pg.locator("#canvas").bounding_box()
    pg.mouse.click(box["x"] + x, box["y"] + y)
    pg.screenshot(path=out)
    b.close()
