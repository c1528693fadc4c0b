// The page `vbusd view --engine babylon` serves: a Virtual Bones asset drawn by Babylon.js with the
// material plugin (web/babylon/src), thin instances, a shadow-casting sun and an orbit camera.
//
// Query parameters as viewer.js's: time=T, paused=1, camera=x,y,z,tx,ty,tz, fov=DEG, silhouette=1,
// ui=0, width=W, height=H, instances=N, antialias=0, skin=attributes|pulled (the skin binding;
// attributes by default). The plain files of a USD asset are parsed by @vbusd/core.
//
// window.vbusd: {ready, probe(instance, time), setTime(t), render(), velocity({texture}),
// measureFrames(n), engine ('babylon'), backend ('webgl2'), babylon: {engine, scene, camera},
// crowds, animations}.

import {
  Engine, Scene, Vector3, Color3, Color4, StandardMaterial, DirectionalLight, HemisphericLight,
  ArcRotateCamera, MeshBuilder, ShadowGenerator, ImportMeshAsync, Tools, Constants,
} from '@babylonjs/core';

import { fetchPlainScene, singleInstance } from '@vbusd/core';
import { measureFrames, pageApi, pageOptions, showError, startPage, velocityImage } from './vbusd-core/viewer.js';

import {
  VirtualBonesAnimation, VirtualBonesCrowd, probeBabylonCrowd, registerVirtualBonesGLTFExtension,
} from './vbusd-babylon/index.js';

const page = pageOptions();
const { params, number, silhouette, element } = page;

async function main() {
  const { config, canvas } = await startPage(page);
  const engine = new Engine(canvas, params.get('antialias') !== '0', { preserveDrawingBuffer: true, stencil: true });
  if (engine.webGLVersion < 2) throw new Error('the Babylon.js runtime needs WebGL 2');
  const scene = new Scene(engine);
  scene.useRightHandedSystem = true;  // vbusd's data is right-handed (USD, glTF): used as stored
  const material = (name) => (silhouette
    ? Object.assign(new StandardMaterial(name, scene), { disableLighting: true, emissiveColor: new Color3(1, 1, 1) })
    : Object.assign(new StandardMaterial(name, scene), { diffuseColor: new Color3(0.72, 0.74, 0.78), specularColor: new Color3(0.1, 0.1, 0.1) }));
  let crowds;
  let animations;
  let zUp = false;
  if (config.kind === 'gltf') {
    // A `vbusd export` package through Babylon's own glTF loader and the VBUSD_virtual_bones extension.
    registerVirtualBonesGLTFExtension({ material });
    await ImportMeshAsync(config.url, scene);
    if (!scene.metadata?.virtualBones) throw new Error('the glTF has no VBUSD_virtual_bones meshes');
    ({ crowds, animations } = scene.metadata.virtualBones);
  } else {
    if (config.kind !== 'scene') throw new Error(`unknown asset kind ${config.kind}`);
    const asset = await fetchPlainScene(config.url);
    zUp = asset.upAxis === 'Z';
    const skin = params.get('skin');
    animations = asset.animations.map((entry) => new VirtualBonesAnimation(scene, entry));
    // Levels of detail (format 1.2): each crowd picks every instance's level before each render.
    const lod = (entry) => ({ levels: entry.levels, screenSizes: entry.screenSizes });
    crowds = asset.crowds.map((crowd) => new VirtualBonesCrowd(scene, {
      animation: animations[crowd.animation], meshes: asset.animations[crowd.animation].meshes,
      instances: crowd.instances, material, name: crowd.name, skin, ...lod(asset.animations[crowd.animation]) }));
    const instanced = new Set(asset.crowds.map((crowd) => crowd.animation));
    asset.animations.forEach((entry, a) => {
      if (!instanced.has(a)) crowds.push(new VirtualBonesCrowd(scene, { animation: animations[a], meshes: entry.meshes, instances: singleInstance(0), material, name: entry.name, skin, ...lod(entry) }));
    });
  }
  if (params.has('instances')) for (const crowd of crowds) crowd.count = number('instances');

  // Frame the instances' rest bounds.
  let min = new Vector3(Infinity, Infinity, Infinity);
  let max = new Vector3(-Infinity, -Infinity, -Infinity);
  for (const crowd of crowds) {
    if (crowd.levels) {  // levels of detail: the instances' boxes (their level meshes draw none yet)
      const box = crowd.boundsOfInstances();
      min = Vector3.Minimize(min, box.min);
      max = Vector3.Maximize(max, box.max);
      continue;
    }
    for (const mesh of crowd.meshes) {
      mesh.thinInstanceRefreshBoundingInfo(false);
      const box = mesh.getBoundingInfo().boundingBox;
      min = Vector3.Minimize(min, box.minimumWorld);
      max = Vector3.Maximize(max, box.maximumWorld);
    }
  }
  const center = min.add(max).scale(0.5);
  const radius = Math.max(max.subtract(min).length() / 2, 1e-3);
  const up = zUp ? new Vector3(0, 0, 1) : new Vector3(0, 1, 0);
  const camera = new ArcRotateCamera('camera', 0, 0, radius * 2.1, center, scene);
  camera.upVector = up;
  if (params.has('camera')) {  // camera=x,y,z,tx,ty,tz: position and target, as viewer.js's
    const c = params.get('camera').split(',').map(Number);
    camera.setTarget(new Vector3(c[3], c[4], c[5]));
    camera.setPosition(new Vector3(c[0], c[1], c[2]));
  } else {
    const side = zUp ? new Vector3(0, -1, 0) : new Vector3(0, 0, 1);
    camera.setPosition(center.add(side.scale(radius * 1.9)).add(up.scale(radius * 0.75)));
  }
  camera.minZ = radius / 500;
  camera.maxZ = radius * 50;
  camera.fov = (number('fov', 40) * Math.PI) / 180;
  camera.attachControl(canvas, true);

  let shadowGenerator = null;
  if (silhouette) {
    scene.clearColor = new Color4(0, 0, 0, 1);
  } else {
    scene.clearColor = Color4.FromHexString('#1d2026ff');
    const sky = new HemisphericLight('sky', up, scene);
    sky.intensity = 0.6;
    sky.groundColor = new Color3(0.23, 0.19, 0.15);
    const sunDirection = up.scale(-2).add(new Vector3(-1, 0, -0.6)).normalize();
    const sun = new DirectionalLight('sun', sunDirection, scene);
    sun.position = center.subtract(sunDirection.scale(radius * 3));
    sun.intensity = 1.6;
    shadowGenerator = new ShadowGenerator(2048, sun);
    shadowGenerator.usePoissonSampling = true;
    for (const crowd of crowds) for (const mesh of crowd.meshes) shadowGenerator.addShadowCaster(mesh);
    const ground = MeshBuilder.CreateDisc('ground', { radius: radius * 6, tessellation: 64 }, scene);
    ground.material = Object.assign(new StandardMaterial('ground', scene), { diffuseColor: new Color3(0.29, 0.31, 0.35), specularColor: new Color3(0, 0, 0) });
    if (zUp) { ground.position = new Vector3(center.x, center.y, min.z); } else { ground.rotation.x = Math.PI / 2; ground.position = new Vector3(center.x, min.y, center.z); }
    ground.receiveShadows = true;
  }

  let time = number('time', 0);
  // Draw only when something changed (time, camera, size), as the three.js viewer does: a paused
  // page that redraws every animation frame keeps a core busy under software WebGL.
  let needsRender = true;
  camera.onViewMatrixChangedObservable.add(() => { needsRender = true; });
  let playing = params.get('paused') !== '1' && !params.has('time');
  // The frame interval of the previous-frame pose (motion vectors, spec 21): ?dt=SECONDS, default
  // 1/60; a playing viewer uses its real frame interval.
  const frameInterval = number('dt', 1 / 60);
  const setTime = (t, dt = frameInterval) => {
    time = t;
    for (const animation of animations) animation.time = t;
    for (const crowd of crowds) crowd.updateSamples(t);  // a fade over stage time
    for (const crowd of crowds) crowd.updatePrevious(t, dt);
    element('time-label').textContent = `${t.toFixed(2)} s`;
    needsRender = true;
  };
  element('play').textContent = playing ? 'Pause' : 'Play';
  element('play').onclick = () => { playing = !playing; element('play').textContent = playing ? 'Pause' : 'Play'; };
  setTime(time);
  const render = () => {
    for (const crowd of crowds) crowd.updateLevels?.(camera);
    scene.render();
    needsRender = false;
  };
  await scene.whenReadyAsync();
  render();
  let last = performance.now();
  engine.runRenderLoop(() => {
    const now = performance.now();
    if (playing) setTime(time + (now - last) / 1000, now > last ? (now - last) / 1000 : frameInterval);
    last = now;
    if (needsRender) render();
    element('stats').textContent = `frame time: ${engine.getDeltaTime().toFixed(1)} ms, ${crowds.reduce((n, c) => n + c.count, 0)} instances`;
  });
  window.addEventListener('resize', () => { engine.resize(); needsRender = true; });

  const gl = engine._gl;
  const pixel = new Uint8Array(4);
  /** The velocity textures Babylon's PrePassRenderer writes from the same previous and current
   * positions (the material plugin's previous skinned pose placed by the crowd's previous
   * thin-instance matrices), decoded into NDC motion (current - previous): 'taa', what
   * TAARenderingPipeline's reprojection reads (PREPASS_VELOCITY_LINEAR: half floats, (previous -
   * current) / 2), and 'motionBlur', what MotionBlurPostProcess reads (PREPASS_VELOCITY: 8 bits,
   * v = sign(d) |d|^(1/3) / 2 + 1/2 of d = (current - previous) / 2, so NDC motion = 2 sign(c) |c|^3,
   * c = 2 v - 1). Babylon writes one of the two at a time. */
  const velocityTextures = {
    taa: { type: Constants.PREPASS_VELOCITY_LINEAR_TEXTURE_TYPE, decode: (value) => -2 * value },
    motionBlur: { type: Constants.PREPASS_VELOCITY_TEXTURE_TYPE,
      decode: (value) => { const c = (2 * value) / 255 - 1; return 2 * Math.sign(c) * Math.abs(c) ** 3; } },
  };
  let velocityPass = null;
  /** velocity()'s image of `texture` (velocityTextures), asked for by a pass post-process that carries
   * it in its pre-pass configuration as those effects do (the bundle does not export PassPostProcess:
   * it is made from Babylon's class registry by name). Two renders: previousViewProjection is the
   * camera of the render before. */
  const babylonVelocity = async ({ texture: name = 'taa' } = {}) => {
    const kind = velocityTextures[name];
    if (!kind) throw new Error(`velocity: no texture '${name}' (${Object.keys(velocityTextures).join(', ')})`);
    if (velocityPass?.vbTexture !== name) {
      velocityPass?.dispose(camera);
      const PassPostProcess = Tools.Instantiate('BABYLON.PassPostProcess');
      velocityPass = new PassPostProcess(`vbusd velocity (${name})`, 1.0, camera);
      velocityPass.vbTexture = name;
      velocityPass._prePassEffectConfiguration = { name: `vbusd ${name} velocity`, enabled: true, texturesRequired: [kind.type] };
      if (!scene.enablePrePassRenderer()) throw new Error('Babylon.js\' pre-pass renderer is not supported here');
      scene.prePassRenderer.markAsDirty();
      await scene.whenReadyAsync();
    }
    render();
    render();
    const prePass = scene.prePassRenderer;
    const target = prePass.defaultRT.textures[prePass.getIndex(kind.type)];
    const { width, height } = target.getSize();
    const pixels = await target.readPixels(0, 0, null, true, false);  // bytes, or float32 from half floats
    return velocityImage(pixels, width, height, { decode: kind.decode, covered: true });
  };
  window.vbusd = {
    engine: 'babylon', backend: 'webgl2', babylon: { engine, scene, camera, shadowGenerator }, crowds, animations,
    /** The camera's projection and view matrices as three.js' pages give them (column-major
     * `elements` of column-vector matrices: Babylon's row-vector `m` arrays, which are the same
     * numbers), for tests that project the decoder's vertices with the page's own camera. */
    camera: {
      get projectionMatrix() { return { elements: Array.from(camera.getProjectionMatrix(true).m) }; },
      get matrixWorldInverse() { return { elements: Array.from(camera.getViewMatrix(true).m) }; },
    },
    setTime, render,
    /** The velocity (motion vectors, spec 21) of the view at the current time and the page's dt: NDC
     * motion since the previous frame, {width, height, rg: row-major from the top row, 2 floats per
     * pixel}, a Promise; `{texture: 'motionBlur'}` reads MotionBlurPostProcess' 8-bit texture instead
     * of TAA's (babylonVelocity). */
    velocity: babylonVelocity,
    // instanceCount, probe(instance, t) (with previousPositions for the page's dt), levels(),
    // measureFrames(n): @vbusd/core's page part; each measured frame is rendered and finished (a
    // pixel read), outside Babylon's render loop.
    ...pageApi(crowds, (crowd, index, t, options) => probeBabylonCrowd(engine, crowd, index, t, options), (frames = 60) => {
      engine.stopRenderLoop();
      return measureFrames(frames, { step: () => setTime(time + 1 / 60), render,
        finish: () => gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, pixel) });
    }, { dt: frameInterval }),
  };
}

window.vbusdReady = main().catch((error) => { showError(error); throw error; });
