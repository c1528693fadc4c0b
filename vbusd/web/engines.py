"""The web engines of ``vbusd view --engine`` and the page that draws the asset with each.

Every page offers the same ``window.vbusd.probe(instance, time)`` (world-space skinned positions
and normals from the GPU), so one browser harness checks every engine against the reference
decoder (docs/engines.md).
"""

from __future__ import annotations

__all__ = ["ENGINES", "ENGINE_PAGES"]

#: Engine names, the default first.
ENGINES = ("three", "three-webgpu", "babylon")

#: The page of each engine (web/viewer/; vbusd/web/static/ of a wheel): three.js mapped to WebGLRenderer's build
#: (index.html) or to three/webgpu (webgpu.html); both run viewer.js.
#: Babylon.js: babylon.html and babylon-viewer.js (the material plugin of web/babylon on thin
#: instances; Babylon's modules bundled once by esbuild).
ENGINE_PAGES = {"three": "/index.html", "three-webgpu": "/webgpu.html", "babylon": "/babylon.html"}
