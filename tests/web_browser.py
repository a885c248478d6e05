"""A real headless browser for the web viewer's tests: Debian's chromium driven by
selenium through chromium-driver. Tests that need it skip, with the reason, where either
is missing (`make test` installs both as root); whatever it started is stopped, also
when a test fails."""

from __future__ import annotations

import contextlib
import importlib.util
import json
import shutil
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import psutil
import pytest

if TYPE_CHECKING:
    from selenium.webdriver.remote.webdriver import WebDriver

CHROMIUM = ("chromium", "chromedriver")  # Debian's chromium and chromium-driver
PAGE_TIMEOUT = 60  # s for a page and its scripts to load


def needs_chromium() -> pytest.MarkDecorator:
    missing = [p for p in CHROMIUM if shutil.which(p) is None]
    if importlib.util.find_spec("selenium") is None:
        missing.append("selenium (the dev extra)")
    return pytest.mark.skipif(
        bool(missing),
        reason=f"no {' or '.join(missing)}: a headless browser needs Debian's chromium "
        "and chromium-driver and selenium (`make test` installs them, the first two as root)",
    )


@dataclass
class Traffic:
    """What the page fetched from one port: requests by URL, bytes received."""

    port: int
    requests: dict[str, str] = field(default_factory=dict)  # request id -> URL
    received: int = 0

    def read(self, driver: WebDriver) -> None:
        """Add the network events logged since the last read."""
        for entry in driver.get_log("performance"):
            message = json.loads(entry["message"])["message"]
            params = message["params"]
            if message["method"] == "Network.requestWillBeSent":
                url = params["request"]["url"]
                if f":{self.port}/" in url:
                    self.requests[params["requestId"]] = url
            elif (
                message["method"] == "Network.dataReceived" and params["requestId"] in self.requests
            ):
                self.received += params["dataLength"]


@contextlib.contextmanager
def chromium(width: int = 1280, height: int = 800) -> Iterator[WebDriver]:
    """A headless chromium (a selenium WebDriver) that logs its network events; quit,
    and its processes killed if they linger, on leaving."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = shutil.which("chromium")
    for argument in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage",
                     f"--window-size={width},{height}", "--hide-scrollbars"):  # fmt: skip
        options.add_argument(argument)
    options.set_capability("goog:loggingPrefs", {"performance": "ALL"})
    service = Service(shutil.which("chromedriver"))
    driver = webdriver.Chrome(service=service, options=options)
    try:
        driver.set_page_load_timeout(PAGE_TIMEOUT)
        # A script waits for the page's thread, which the viewer holds while it takes in
        # a recording: past Selenium's 30 s on a loaded 2-core host.
        driver.set_script_timeout(PAGE_TIMEOUT)
        yield driver
    finally:
        tree = [psutil.Process(service.process.pid)]
        with contextlib.suppress(psutil.NoSuchProcess):
            tree += tree[0].children(recursive=True)
        with contextlib.suppress(Exception):
            driver.quit()
        for process in tree:
            with contextlib.suppress(psutil.NoSuchProcess):
                process.kill()
        with contextlib.suppress(subprocess.TimeoutExpired):
            service.process.wait(timeout=10)
