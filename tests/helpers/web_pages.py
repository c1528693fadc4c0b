"""The files an engine's page loads, found by following its HTML, its import map and its modules'
imports (static and dynamic): what the wheel's build step and `vbusd view` must provide."""

from __future__ import annotations

import json
import re
from pathlib import Path
from urllib.parse import urljoin

__all__ = ["page_files", "folder_fetch"]

_IMPORT_MAP = re.compile(r'<script type="importmap">(.*?)</script>', re.S)
_PAGE_MODULE = re.compile(r'<script type="module" src="([^"]+)"')
_STYLESHEET = re.compile(r'<link rel="stylesheet" href="([^"]+)"')
_STATIC_IMPORT = re.compile(r'^\s*(?:import|export)\b[^;]*?\bfrom\s*[\'"]([^\'"]+)[\'"]', re.M)
_BARE_IMPORT = re.compile(r'^\s*import\s*[\'"]([^\'"]+)[\'"]', re.M)
_DYNAMIC_IMPORT = re.compile(r'\bimport\(\s*[\'"]([^\'"]+)[\'"]\s*\)')
_MINIFIED_IMPORT = re.compile(r'(?:^|[;}])\s*(?:import|export)\s*(?:\{[^}]*\}|\*\s*as\s*\w+|\w+)?\s*from\s*"([^"]+)"')


def _resolve(specifier: str, importer: str, imports: dict):
    """The URL path a module specifier names: relative to its importer, or through the import map
    (an exact key, else the longest key ending in ``/`` that prefixes it); None when unmapped."""
    if specifier.startswith(("./", "../", "/")):
        return urljoin(importer, specifier)
    if specifier in imports:
        return urljoin("/", imports[specifier])
    prefixes = [key for key in imports if key.endswith("/") and specifier.startswith(key)]
    if not prefixes:
        return None
    key = max(prefixes, key=len)
    return urljoin("/", imports[key] + specifier[len(key):])


def page_files(fetch, page: str) -> set:
    """Every URL path one engine's page loads: the page, its stylesheet, its module and everything
    that module imports, statically or with ``import()``, through the page's import map.

    A module reached through ``import()`` may serve another page (viewer.js imports the WebGPU
    runtime only on webgpu.html): its imports that this page's map does not map are not followed.
    Everything reached by static imports must resolve and be served.

    Args:
        fetch: URL path -> the file's text, or None when it is not served.
        page: The page's URL path (``/index.html``).

    Returns:
        The URL paths.
    """
    html = fetch(page)
    assert html is not None, page
    imports = json.loads(_IMPORT_MAP.search(html).group(1))["imports"]
    seen = {page} | {urljoin(page, href) for href in _STYLESHEET.findall(html)}
    for url in sorted(seen):
        assert fetch(url) is not None, url
    queue = [(urljoin(page, src), False) for src in _PAGE_MODULE.findall(html)]
    assert queue, page
    optional_seen = set()
    while queue:
        url, optional = queue.pop()
        if url in seen or (optional and url in optional_seen):
            continue
        text = fetch(url)
        if optional:
            if text is None:
                continue
            optional_seen.add(url)
        else:
            assert text is not None, f"{page} needs {url}, which is not served"
            seen.add(url)
        minified = "\n" not in text[:2000]
        found = [(specifier, optional) for pattern in ((_MINIFIED_IMPORT,) if minified else (_STATIC_IMPORT, _BARE_IMPORT))
                 for specifier in pattern.findall(text)]
        found += [(specifier, True) for specifier in ([] if minified else _DYNAMIC_IMPORT.findall(text))]
        for specifier, lenient in found:
            target = _resolve(specifier, url, imports)
            if target is None:
                assert lenient, f"{url} imports {specifier!r}, which the import map of {page} does not map"
                continue
            queue.append((target, lenient))
    return seen | optional_seen


def folder_fetch(root: Path):
    def fetch(url: str):
        path = root / url.lstrip("/")
        return path.read_text(encoding="utf-8") if path.is_file() else None
    return fetch
