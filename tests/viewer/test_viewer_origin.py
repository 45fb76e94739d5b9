"""The served viewer accepts websocket connections only from its own origin: a page from another
origin open in the same browser cannot read the scene or press Generate."""

from __future__ import annotations

import pytest
from tesseract4d.testing.synthetic_scene import analytic_episode

from reconstruction.backproject import recon_from_episode
from viewer.app import ViewerApp
from viewer.origin import origin_allowed


def _connect(url: str, origin: str | None):
    import viser
    from websockets.sync.client import connect

    ws_url = url.replace("http://", "ws://")
    kwargs = {"origin": origin} if origin is not None else {}
    return connect(ws_url, subprotocols=[f"viser-v{viser.__version__}"], open_timeout=20, **kwargs)


@pytest.fixture(scope="module")
def app():
    recon = recon_from_episode(analytic_episode(num_frames=2, height=32, width=32))
    with ViewerApp(recon, port=0, max_points=500) as running:
        yield running


@pytest.mark.parametrize("origin", ["http://evil.example", "http://evil.example:{port}", "http://127.0.0.1:1",
                                    "https://127.0.0.1.evil.example:{port}", "null", "file://", "http://localhost"])
def test_a_foreign_origin_is_refused(app, origin):
    from websockets.exceptions import InvalidStatus

    origin = origin.format(port=app.server.get_port())
    with pytest.raises(InvalidStatus) as e:
        _connect(app.url, origin).close()
    assert e.value.response.status_code == 403


@pytest.mark.parametrize("origin", ["served", "http://localhost:{port}", "http://[::1]:{port}", None])
def test_the_served_origin_is_accepted_and_gets_the_scene(app, origin):
    origin = app.url if origin == "served" else origin and origin.format(port=app.server.get_port())
    with _connect(app.url, origin) as ws:
        assert len(ws.recv(timeout=20)) > 0  # the scene's first messages arrive


def test_the_allow_list():
    assert origin_allowed("http://10.0.0.5:8080", "0.0.0.0", ("10.0.0.5", 8080))
    assert origin_allowed("http://localhost:8080", "0.0.0.0", ("127.0.0.1", 8080))
    assert not origin_allowed("http://10.0.0.5:8081", "0.0.0.0", ("10.0.0.5", 8080))
    assert not origin_allowed("http://attacker.example:8080", "0.0.0.0", ("10.0.0.5", 8080))  # DNS rebinding
    assert origin_allowed("http://10.0.0.5:8080", "10.0.0.5", ("10.0.0.5", 8080))
    assert not origin_allowed("http://localhost:8080", "10.0.0.5", ("10.0.0.5", 8080))
    assert not origin_allowed("http://[::1", "127.0.0.1", ("127.0.0.1", 8080))


@pytest.mark.browser
def test_in_a_real_browser_the_viewer_page_connects_and_a_foreign_page_cannot(app, tmp_path):
    """Chromium: the viewer's own page connects and draws the scene; a page served from another
    origin (another port of the same host) that opens a websocket to the viewer is refused."""
    import functools
    import http.server
    import threading

    import viser
    from tesseract4d.testing.browser import chromium, wait_until_drawn

    (tmp_path / "index.html").write_text("<html><body>a page from another origin</body></html>")
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(tmp_path))
    other = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=other.serve_forever, daemon=True).start()
    probe = """(url) => new Promise((resolve) => {
        const ws = new WebSocket(url, [PROTOCOL]);
        ws.onopen = () => { resolve("open"); ws.close(); };
        ws.onerror = () => resolve("refused");
        setTimeout(() => resolve("timeout"), 15000);
    })""".replace("PROTOCOL", repr(f"viser-v{viser.__version__}"))
    ws_url = app.url.replace("http://", "ws://")
    try:
        with chromium() as page:
            page.goto(f"http://127.0.0.1:{other.server_address[1]}/index.html")
            assert page.evaluate(probe, ws_url) == "refused"
            page.goto(app.url)
            wait_until_drawn(page, timeout_s=90)  # the served page's own connection works
            assert page.evaluate(probe, ws_url) == "open"
    finally:
        other.shutdown()
