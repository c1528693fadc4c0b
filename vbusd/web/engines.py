"""The web engines of ``vbusd view --engine`` and the page that draws the asset with each.

Every page offers the same ``window.vbusd.probe(instance, time)`` (world-space skinned positions
and normals from the GPU), so one browser harness checks every engine against the reference
decoder (docs/engines.md).
"""

from __future__ import annotations

__all__ = ["ENGINES", "ENGINE_PAGES"]

#: Engine names, the default first.
ENGINES = ("three", "three-webgpu")

#: The page of each engine under vbusd/web/static: three.js mapped to WebGLRenderer's build
#: (index.html) or to three/webgpu (webgpu.html); both run viewer.js.
ENGINE_PAGES = {"three": "/index.html", "three-webgpu": "/webgpu.html"}
