"""The interactive HTML view: self-contained, checked input, and drawn by a real browser.

The browser tests run headless Chromium (``chromium`` on PATH, as Debian's package installs
it) and skip where there is none.
"""

from __future__ import annotations

import re
import shutil
import subprocess

import cv2
import numpy as np
import pytest

from posernet.sfm.synthetic import make_scene
from posernet.viewer import write_html_view

BROWSER = next((shutil.which(b) for b in ("chromium", "chromium-browser", "google-chrome")
                if shutil.which(b)), None)
needs_browser = pytest.mark.skipif(BROWSER is None, reason="no headless Chromium installed")


def _scene(n: int = 10, gt_noise: float = 0.1):
    s = make_scene(num_cameras=n, num_points=500, seed=1)
    rng = np.random.default_rng(0)
    cams, gt = {}, {}
    for i, T in enumerate(s.w2c):
        c2w = np.linalg.inv(T)
        name = f"img{i:02d}.png"
        cams[name] = {"camera_to_world": c2w.tolist(), "K": s.K[i].tolist(), "size": [640, 480],
                      "component": 0 if i < n - 2 else 1, "solved": True}
        g = c2w.copy()
        g[:3, 3] += rng.normal(0, gt_noise, 3)
        gt[name] = g
    colours = np.tile([[0, 160, 0]], (len(s.points), 1))
    return cams, s.points, colours, gt


def _browser(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([BROWSER, "--headless", "--no-sandbox", "--disable-gpu",
                           "--hide-scrollbars", *args], capture_output=True, text=True,
                          timeout=120)


def test_page_is_self_contained_and_escapes_names(tmp_path):
    cams, pts, col, gt = _scene()
    cams["evil</script><b>.png"] = dict(cams.pop("img00.png"))
    gt.pop("img00.png")
    page = write_html_view(tmp_path / "v.html", cams, pts, col, ground_truth=gt,
                           title="a <b>bold</b> title").read_text()
    assert "<b>bold</b>" not in page and "a &lt;b&gt;bold&lt;/b&gt; title" in page
    assert "evil</script>" not in page and "evil<\\/script>" in page
    # offline: nothing fetched (no script, style, font or image from elsewhere)
    assert not re.search(r"""(src|href)\s*=\s*["']?(https?:)?//""", page)
    assert "@import" not in page and "url(" not in page


def test_unsolved_cameras_are_left_out_and_bad_input_is_named(tmp_path):
    cams, pts, col, _ = _scene()
    cams["img03.png"] = {"solved": False, "camera_to_world": None}
    page = write_html_view(tmp_path / "v.html", cams, pts, col).read_text()
    assert '"name":"img03.png"' not in page and '"name":"img04.png"' in page
    with pytest.raises(ValueError, match="no solved camera"):
        write_html_view(tmp_path / "none.html", {"a": {"solved": False}})
    cams["img05.png"]["camera_to_world"] = [[1.0, 0, 0], [0, 1, 0]]
    with pytest.raises(ValueError, match="camera 'img05.png'.*4x4"):
        write_html_view(tmp_path / "bad.html", cams)
    assert not (tmp_path / "bad.html").exists()
    cams, pts, col, _ = _scene()
    with pytest.raises(ValueError, match="colours: 3 rows for 500 points"):
        write_html_view(tmp_path / "bad.html", cams, pts, col[:3])


def test_many_points_are_subsampled(tmp_path):
    cams, _, _, _ = _scene()
    pts = np.random.default_rng(0).normal(size=(5000, 3))
    page = write_html_view(tmp_path / "v.html", cams, pts, max_points=300).read_text()
    data = re.search(r'"points":\[([^\]]*)\]', page).group(1)
    assert len(data.split(",")) == 3 * 300


def _data(page: str) -> dict:
    import json

    return json.loads(re.search(r'<script id="data" type="application/json">(.*?)</script>',
                                page, re.S).group(1).replace("<\\/", "</"))


def test_status_counts_the_points_given_like_the_title(tmp_path):
    """Points far from the cameras, not finite or thinned out are not drawn: the status line
    still counts every point given (the title's number) and says how many are drawn."""
    cams, pts, col, _ = _scene()
    far = np.array([[1e4, 0, 0], [0, -2e4, 0], [np.nan, 0, 0]])
    pts, col = np.concatenate([pts, far]), np.concatenate([col, col[:3]])
    title = f"10 of 10 cameras, {len(pts)} points"
    data = _data(write_html_view(tmp_path / "v.html", cams, pts, col, title=title).read_text())
    assert data["status"] == ("10 cameras, 503 points (500 drawn; left out: 1 not finite, "
                              "2 far from the cameras), 2 components")
    assert len(data["points"]) == 3 * 500
    data = _data(write_html_view(tmp_path / "v.html", cams, pts, col, max_points=100)
                 .read_text())
    assert data["status"] == ("10 cameras, 503 points (99 drawn; left out: 1 not finite, 402 "
                              "thinned out, 1 far from the cameras), 2 components")
    cams.pop("img08.png"), cams.pop("img09.png")  # one component, every point drawn
    data = _data(write_html_view(tmp_path / "v.html", cams, pts[:500], col[:500]).read_text())
    assert data["status"] == "8 cameras, 500 points"


@needs_browser
def test_browser_draws_cameras_points_and_ground_truth(tmp_path):
    cams, pts, col, gt = _scene()
    path = write_html_view(tmp_path / "view.html", cams, pts, col, ground_truth=gt, units="m")
    dom = _browser("--dump-dom", path.as_uri()).stdout
    assert 'data-rendered="1"' in dom, dom[-2000:]  # the script ran to its end
    assert "10 cameras, 500 points, 2 components" in dom
    far = write_html_view(tmp_path / "far.html", cams, np.concatenate([pts, [[1e4, 0, 0]]]),
                          title="10 cameras, 501 points")
    far_dom = _browser("--dump-dom", far.as_uri()).stdout
    assert ('<div id="status">10 cameras, 501 points (500 drawn; left out: 1 far from the '
            'cameras), 2 components</div>') in far_dom, far_dom[-2000:]
    assert "largest component: 8 cameras" in dom and "component 2: 2 cameras" in dom
    assert "ground truth (linked to its estimate)" in dom and "units: m" in dom
    shots = []
    for view in ("", "#yaw=120&pitch=-30&zoom=0.7"):
        png = tmp_path / f"shot{len(shots)}.png"
        _browser("--window-size=900,700", f"--screenshot={png}", path.as_uri() + view)
        img = cv2.imread(str(png))
        assert img is not None, f"no screenshot for view {view!r}"
        b, g, r = (img[..., k].astype(int) for k in range(3))
        red = (r > 150) & (g < 90) & (b < 90)  # the largest component's frustums (#d62728)
        green = (g > 120) & (r < 60) & (b < 60)  # the points
        assert red.sum() > 200 and green.sum() > 200, (red.sum(), green.sum())
        shots.append(red)
    # the view from the address's # part is another view of the same scene
    assert (shots[0] != shots[1]).mean() > 0.002
