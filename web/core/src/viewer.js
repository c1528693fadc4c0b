// What every `vbusd view` page does whatever its engine (web/viewer/viewer.js for three.js WebGL
// and WebGPU, web/viewer/babylon-viewer.js for Babylon.js): the query parameters, the page's title,
// panel and canvas size, errors shown on the page, and window.vbusd's engine-neutral part (the
// probe's instance numbering, the levels drawn, the frame-time measurement). Not part of the npm
// package's entry point: the pages import it from the served core folder.

/** The page's query parameters and DOM helpers: `{params, number(name, fallback), silhouette, element(id)}`. */
export function pageOptions(search = window.location.search) {
  const params = new URLSearchParams(search);
  return {
    params,
    number: (name, fallback) => (params.has(name) ? Number(params.get(name)) : fallback),
    silhouette: params.get('silhouette') === '1',
    element: (id) => document.getElementById(id),
  };
}

/** Log `error` and show its message in the page's #error line (the tests read it there). */
export function showError(error) {
  console.error(error);
  document.getElementById('error').textContent = String(error?.message ?? error);
}

/**
 * Fetch config.json (what `vbusd view` serves: the asset's name, kind, URL and engine), title the
 * page after it, hide the panel with ui=0 and size the canvas with width= and height= (CSS pixels).
 * Returns `{config, canvas}`.
 */
export async function startPage({ params, number, element }) {
  const config = await (await fetch('config.json')).json();
  element('title').textContent = config.name;
  document.title = `vbusd view: ${config.name}`;
  if (params.get('ui') === '0') element('panel').classList.add('hidden');
  const canvas = element('view');
  if (params.has('width')) {
    canvas.style.width = `${number('width')}px`;
    canvas.style.height = `${number('height')}px`;
  }
  return { config, canvas };
}

/**
 * window.vbusd's engine-neutral members over `crowds` (in the order the page numbers instances:
 * each crowd's instances in turn): `instanceCount`, `probe(instance, t)` through the engine's
 * `probeOne(crowd, index, t, {dt})` (a result or a promise of `{positions, normals, lod}` and, for
 * the previous-frame pose, `previousPositions`), `levels()` and `measureFrames(frames)` through
 * `measure`. `dt`: the page's frame interval (?dt=SECONDS, default 1/60; spec virtual-bones.md 21),
 * the interval the probe's previous pose is taken over.
 */
export function pageApi(crowds, probeOne, measure, { dt = 1 / 60 } = {}) {
  const targets = crowds.flatMap((crowd) => Array.from({ length: crowd.capacity }, (_, i) => [crowd, i]));
  return {
    get instanceCount() { return targets.length; },
    /** World-space skinned vertices of instance `instance` at time `t` (seconds), from the GPU,
     * `lod`: the level of detail it was drawn with at the last render (-1: culled; 0 without levels;
     * the vertices are that level's, LOD 0's when culled), `previousPositions`: the previous-frame
     * pose for the page's frame interval `dt` (spec 21), and what it shows (format 1.3 crowd
     * variety): `tint`, `variant`, `variantName`, `parts`, `partNames`. `{previous: false}` leaves
     * `previousPositions` null (WebGPU then compiles no second compute pass: seconds on software). */
    async probe(instance, t, { previous = true } = {}) {
      const target = targets[instance];
      if (!target) throw new Error(`no instance ${instance} (the viewer has ${targets.length})`);
      const result = await probeOne(target[0], target[1], t, { dt, previous });
      return { positions: Array.from(result.positions), normals: Array.from(result.normals),
        previousPositions: previous ? Array.from(result.previousPositions ?? []) : null, dt, lod: result.lod,
        ...(target[0].varietyOf ? target[0].varietyOf(target[1]) : {}) };
    },
    /** Levels of detail drawn at the last render: per instance (probe numbering), and triangles drawn. */
    levels() {
      return {
        lod: targets.map(([crowd, i]) => crowd.levelOf(i)),
        triangles: crowds.reduce((n, crowd) => n + crowd.trianglesDrawn, 0),
      };
    },
    measureFrames: measure,
  };
}

/**
 * window.vbusd.velocity()'s image from an RGBA texture read back from the GPU (`pixels`, rows
 * bottom first as WebGL reads them unless `upward` is false): `{width, height, rg}`, rg row-major
 * from the top row, 2 numbers a pixel, `decode` of the texture's red and green (NDC motion); with
 * `covered`, a pixel whose alpha is 0 (nothing drawn) is 0, whatever its code.
 */
export function velocityImage(pixels, width, height, { upward = true, decode = (value) => value, covered = false } = {}) {
  const rg = new Array(2 * width * height);
  for (let y = 0; y < height; ++y) {
    const row = upward ? height - 1 - y : y;
    for (let x = 0; x < width; ++x) {
      const k = 4 * (row * width + x);
      const empty = covered && pixels[k + 3] === 0;
      rg[2 * (y * width + x)] = empty ? 0 : decode(pixels[k]);
      rg[2 * (y * width + x) + 1] = empty ? 0 : decode(pixels[k + 1]);
    }
  }
  return { width, height, rg };
}

/**
 * Mean milliseconds per frame over `frames` frames, each the clock advanced one 60 Hz step
 * (`step`), rendered (`render`) and finished (`finish`: a pixel read back, or the GPU queue
 * drained; it may return a promise, awaited before the next frame). A promise of the mean.
 */
export async function measureFrames(frames, { step, render, finish }) {
  render();
  await finish();
  const start = performance.now();
  for (let i = 0; i < frames; ++i) {
    step();
    render();
    await finish();
  }
  return (performance.now() - start) / frames;
}
