"""What the test modules share: import as ``from tests.helpers import ...`` (never by path).

* :mod:`tests.helpers.capabilities`: what the machine offers (browser, EGL/GL, Node ...) and what a
  run requires; ``require(NAME)``.
* :mod:`tests.helpers.fixtures`: the session fixtures (browsers, converted assets, shared assets),
  loaded by tests/conftest.py.
* :mod:`tests.helpers.browser`: the browser probe, silhouette and covering matrix.
* :mod:`tests.helpers.node`: the Node scripts of tests/node.
* :mod:`tests.helpers.cli`: the ``vbusd`` command run in-process, with its output captured.
* :mod:`tests.helpers.once`: a costly read-only input (a wheel, a trace) made once per test run for
  all xdist workers.
* :mod:`tests.helpers.scenes`: small UsdSkel scenes written from code.
* :mod:`tests.helpers.gl_module`: a ``vbusd shader`` module (``--previous`` or not) run by OpenGL
  transform feedback (GLSL, and HLSL through glslang and spirv-cross): the shader tests' one harness.
* :mod:`tests.helpers.scripts`: repository scripts under test (samples/, spec/, scripts/) loaded by
  path, once.
* the benchmarks' harnesses, whose logic tests check and whose command lines are benchmarks/*.py:
  :mod:`tests.helpers.draw_cost`, :mod:`tests.helpers.accuracy`, :mod:`tests.helpers.mutation_run`,
  :mod:`tests.helpers.engines_side_by_side`.
"""
