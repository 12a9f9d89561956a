"""A clear message in the page when the server is gone.

viser's page keeps showing the last scene when its websocket closes (it only tries to reconnect),
so an annotator could go on clicking into a page that saves nothing. :data:`SERVER_WATCH_SHIM`
(added to every page as a GUI HTML element; viser runs no <script>, an inline error handler runs
once) asks the server for a tiny URL every :data:`PING_MS` ms; while no answer comes it covers
the page with a red banner saying the server is gone, that every edit acknowledged with
"✓ saved" is safe, and how to go on. Any HTTP answer (a 404 too) means the server is up; the
banner then asks for a page reload (viser's page does not rebuild the app's panels by itself).
"""

from __future__ import annotations

import html

PING_MS = 2000
GONE_TITLE = "The handanno server is gone"
GONE_TEXT = (
    "Nothing you do in this page is saved now. Every edit shown as '✓ saved' is safe on disk. "
    "Restart the server (handanno serve SESSION) and reload this page."
)
BACK_TEXT = "The server is back: reload this page to go on annotating."

_JS = """
if (!window.__handannoWatch) {
  window.__handannoWatch = true;
  let banner = null;
  const show = (title, text, colour) => {
    if (!banner) {
      banner = document.createElement("div");
      banner.id = "handanno-server-gone";
      banner.setAttribute("role", "alert");
      banner.style.cssText = "position:fixed;top:0;left:0;right:0;z-index:100000;padding:14px;" +
        "font:16px sans-serif;color:white;text-align:center";
      document.body.appendChild(banner);
    }
    banner.style.background = colour;
    banner.textContent = title ? title + ". " + text : text;
  };
  let gone = false;
  const ping = () => {
    fetch("/handanno-ping?" + Date.now(), {cache: "no-store"}).then(() => {
      if (gone) show("", BACK_TEXT, "#1c7c54");
    }).catch(() => { gone = true; show(GONE_TITLE, GONE_TEXT, "#c92a2a"); });
  };
  setInterval(ping, PING_MS);
}
"""
for _name, _value in (
    ("BACK_TEXT", BACK_TEXT),
    ("GONE_TITLE", GONE_TITLE),
    ("GONE_TEXT", GONE_TEXT),
    ("PING_MS", PING_MS),
):
    _JS = _JS.replace(_name, repr(_value) if isinstance(_value, str) else str(_value))
SERVER_WATCH_SHIM = (
    '<img alt="" src="data:," style="display:none" onerror="'
    + html.escape(" ".join(_JS.split()))
    + '">'
)
