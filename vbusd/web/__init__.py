"""The browser side of vbusd: the three.js viewer that ``vbusd view`` serves.

* :mod:`vbusd.web.shader_modules` writes the JavaScript module of GLSL strings that the three.js
  runtime (``web/`` in the repository) patches into three's materials, generated from
  :mod:`vbusd.decoders.shaders` so the browser runs the very module ``vbusd shader`` prints;
* :mod:`vbusd.web.scene` turns a Virtual Bones asset into the viewer's plain files (a JSON
  description and one binary buffer of texels, meshes and instances);
* :mod:`vbusd.web.server` serves the viewer page, three.js and the asset on 127.0.0.1.

The pages, the runtimes, three.js and the Babylon.js bundle live once in the repository's ``web/``
(:mod:`vbusd.web.static_files` says which file each URL is); a checkout serves them from there, and
the wheel ships a copy under ``static/`` made when it is built, so the viewer works offline.
"""
