// The page `vbusd view` serves: a Virtual Bones asset or crowd in three.js, with an orbit camera,
// play/pause, time scrub, clip picker, instance count and frame time.
//
// Query parameters (tests, screenshots and benchmarks use them): time=T (start at T seconds),
// paused=1, camera=x,y,z,tx,ty,tz (position and target), fov=DEG, silhouette=1 (unlit white on
// black, no ground, fog or tone mapping), ui=0 (no panel), antialias=0, instances=N, width=W and
// height=H (fixed canvas size in CSS pixels), pixelRatio=R, skin=attributes|pulled (the skin binding).
//
// The engine comes from config.json (`vbusd view --engine`): `three` (WebGLRenderer, index.html) or
// `three-webgpu` (WebGPURenderer and the TSL runtime, webgpu.html, which maps three to
// three/webgpu); with three-webgpu, backend=webgl forces WebGPURenderer's WebGL 2 backend.
//
// window.vbusd: {ready (a Promise), probe(instance, time), levels(), setTime(t), render(), measureFrames(n),
// renderer, scene, camera, crowds, engine, backend}. probe numbers instances across the crowds in the asset's order,
// then one per animation that no crowd instances.

import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';

import {
  buildObjects, loadPlainScene, probeCrowd, renderVelocity, VirtualBonesGLTFPlugin, descriptionFromGLTF,
} from './vbusd-three/index.js';
import { measureFrames, pageApi, pageOptions, showError, startPage, velocityImage } from './vbusd-core/viewer.js';

const page = pageOptions();
const { params, number, silhouette, element } = page;

async function loadDescription(config) {
  if (config.kind === 'scene') return loadPlainScene(config.url);
  if (config.kind === 'gltf') {
    const loader = new GLTFLoader();
    loader.register((parser) => new VirtualBonesGLTFPlugin(parser));
    const gltf = await loader.loadAsync(config.url);
    return descriptionFromGLTF(gltf);
  }
  throw new Error(`unknown asset kind ${config.kind}`);
}

async function main() {
  const { config, canvas } = await startPage(page);
  const engine = config.engine ?? 'three';
  const antialias = params.get('antialias') !== '0';
  let renderer;
  let webgpu = null;  // the TSL runtime, with three-webgpu
  if (engine === 'three-webgpu') {
    webgpu = await import('./vbusd-three/webgpu/index.js');
    renderer = new THREE.WebGPURenderer({ canvas, antialias, forceWebGL: params.get('backend') === 'webgl' });
    await renderer.init();
  } else {
    renderer = new THREE.WebGLRenderer({ canvas, antialias, preserveDrawingBuffer: true });
  }
  const backend = webgpu ? (renderer.backend.isWebGPUBackend ? 'webgpu' : 'webgl2') : 'webgl2';
  renderer.setPixelRatio(number('pixelRatio', window.devicePixelRatio));
  const scene = new THREE.Scene();
  const description = await loadDescription(config);
  const zUp = description.upAxis === 'Z';

  // Node materials for WebGPURenderer (the TSL runtime skins those), three's classic ones for WebGL.
  const Basic = webgpu ? THREE.MeshBasicNodeMaterial : THREE.MeshBasicMaterial;
  const Standard = webgpu ? THREE.MeshStandardNodeMaterial : THREE.MeshStandardMaterial;
  const material = silhouette ? () => new Basic({ color: 0xffffff })
    : () => new Standard({ color: 0xb7bcc6, roughness: 0.65, metalness: 0.0 });
  // ?skin=pulled: the skin read by vertex index from skin records (spec/shaders.md, Skin bindings):
  // a texture on WebGL 2, a storage buffer on WebGPU. WebGL's default is DEFAULT_SKIN (pulled), the
  // WebGPU runtime's `attributes`.
  // ?velocity=0 (WebGPU): the crowd writes no previous pose to the velocity output (its motion
  // vectors are its placement's only), for comparison with vbusd's (docs/engines.md, the TRAA picture).
  const previousPose = params.get('velocity') !== '0';
  const skinMaterial = webgpu ? (m, a, k, binding) => webgpu.skinNodeMaterial(m, a, k, { ...binding, previousPose }) : null;
  const objects = buildObjects(description, { material, skin: params.get('skin') ?? (webgpu ? 'attributes' : null), skinMaterial });
  for (const animation of objects.animations) {
    if (webgpu) webgpu.checkNodeSupport(renderer, animation);
    else animation.checkSupport(renderer);
  }
  scene.add(objects.group);
  const crowds = objects.crowds;
  if (params.has('instances')) for (const crowd of crowds) crowd.count = number('instances');

  // Frame everything drawn: the union of the crowds' culling bounds (or their rest bounds).
  const bounds = new THREE.Box3();
  for (const crowd of crowds) {
    if (crowd.levels) {  // levels of detail: the instances' boxes (their level meshes draw none yet)
      bounds.union(crowd.boundsOfInstances());
      continue;
    }
    for (const mesh of crowd.meshes) {
      mesh.computeBoundingBox();
      bounds.union(mesh.boundingBox.clone().applyMatrix4(mesh.matrixWorld));
    }
  }
  const sphere = bounds.getBoundingSphere(new THREE.Sphere());
  const radius = Math.max(sphere.radius, 1e-3);

  const camera = new THREE.PerspectiveCamera(number('fov', 40), 1, radius / 500, radius * 50);
  const up = zUp ? new THREE.Vector3(0, 0, 1) : new THREE.Vector3(0, 1, 0);
  camera.up.copy(up);
  const controls = new OrbitControls(camera, canvas);
  if (params.has('camera')) {
    const c = params.get('camera').split(',').map(Number);
    camera.position.set(c[0], c[1], c[2]);
    controls.target.set(c[3], c[4], c[5]);
  } else {
    const side = zUp ? new THREE.Vector3(0, -1, 0) : new THREE.Vector3(0, 0, 1);
    camera.position.copy(sphere.center).addScaledVector(side, radius * 1.9).addScaledVector(up, radius * 0.75);
    controls.target.copy(sphere.center);
  }
  controls.update();

  if (silhouette) {
    scene.background = new THREE.Color(0x000000);
    renderer.toneMapping = THREE.NoToneMapping;
  } else {
    scene.background = new THREE.Color(0x1d2026);
    scene.fog = new THREE.Fog(0x1d2026, radius * 3, radius * 8);
    renderer.toneMapping = THREE.ACESFilmicToneMapping;
    renderer.shadowMap.enabled = true;
    renderer.shadowMap.type = THREE.PCFShadowMap;
    scene.add(new THREE.HemisphereLight(0xdfe8ff, 0x3a3026, 1.4));
    const sun = new THREE.DirectionalLight(0xffffff, 2.2);
    sun.position.copy(sphere.center).addScaledVector(up, radius * 2).add(new THREE.Vector3(radius, 0, radius * 0.6));
    sun.target.position.copy(sphere.center);
    sun.castShadow = true;
    sun.shadow.mapSize.set(2048, 2048);
    const s = sun.shadow.camera;
    s.left = s.bottom = -radius * 1.2;
    s.right = s.top = radius * 1.2;
    s.near = radius * 0.1;
    s.far = radius * 5;
    sun.shadow.bias = -0.0005;
    scene.add(sun, sun.target);
    const ground = new THREE.Mesh(new THREE.CircleGeometry(radius * 6, 64),
      new Standard({ color: 0x4a505a, roughness: 0.95 }));
    if (!zUp) ground.rotation.x = -Math.PI / 2;
    ground.position.copy(sphere.center);
    if (zUp) ground.position.z = bounds.min.z; else ground.position.y = bounds.min.y;
    ground.receiveShadow = true;
    scene.add(ground);
  }

  // Clock, clip picker and instance count.
  let time = number('time', 0);
  let playing = params.get('paused') !== '1' && !params.has('time');
  let needsRender = true;  // paused and unchanged: no frame is drawn (software WebGL is slow)
  controls.addEventListener('change', () => { needsRender = true; });
  // The frame interval of the previous-frame pose (motion vectors, spec 21): ?dt=SECONDS, default
  // 1/60; a playing viewer uses its real frame interval.
  const frameInterval = number('dt', 1 / 60);
  const setTime = (t, dt = frameInterval) => {
    needsRender = true;
    time = t;
    for (const animation of objects.animations) animation.time = t;
    for (const crowd of crowds) crowd.updateSamples(t);  // a fade over stage time
    for (const crowd of crowds) crowd.updatePrevious(t, dt);
    element('time').value = String(t % Number(element('time').max));
    element('time-label').textContent = `${t.toFixed(2)} s`;
  };
  const longest = Math.max(...objects.animations.flatMap((a) => a.clips.map((c) => (c.loop ? c.rowCount : c.rowCount - 1) / c.rowsPerSecond)), 1e-3);
  element('time').max = String(longest);
  element('play').textContent = playing ? 'Pause' : 'Play';
  element('play').onclick = () => { playing = !playing; element('play').textContent = playing ? 'Pause' : 'Play'; };
  element('time').oninput = () => { playing = false; element('play').textContent = 'Play'; setTime(Number(element('time').value)); };
  const clipNames = [...new Set(objects.animations.flatMap((a) => a.clips.map((c) => c.name)))];
  for (const name of clipNames) element('clip').add(new Option(name, name));
  const authored = crowds.map((crowd) => crowd.clipAttribute.array.slice());
  element('clip').onchange = () => {
    const choice = element('clip').value;
    crowds.forEach((crowd, c) => {
      const index = crowd.animation.clipIndex(choice);
      const clips = choice === '-1' || index < 0 ? authored[c] : authored[c].map(() => index);
      // A clip switch: no motion vector across it (spec 21's reset).
      clips.forEach((clip, i) => { if (crowd.clipAttribute.array[i] !== clip) crowd.resetPrevious(i); });
      crowd.clipAttribute.array.set(clips);
      crowd.updatePrevious(time, frameInterval);
      crowd.clipAttribute.needsUpdate = true;
      crowd.updateBounds();
    });
    needsRender = true;
  };
  const capacity = Math.max(...crowds.map((crowd) => crowd.capacity));
  element('count').max = String(capacity);
  element('count').value = String(Math.max(...crowds.map((crowd) => crowd.count)));
  element('count-label').textContent = element('count').value;
  element('count').oninput = () => {
    for (const crowd of crowds) crowd.count = Number(element('count').value);
    element('count-label').textContent = element('count').value;
    needsRender = true;
  };

  const resize = () => {
    const width = canvas.clientWidth;
    const height = canvas.clientHeight;
    if (canvas.width !== Math.floor(width * renderer.getPixelRatio()) || canvas.height !== Math.floor(height * renderer.getPixelRatio())) {
      renderer.setSize(width, height, false);
      camera.aspect = width / height;
      camera.updateProjectionMatrix();
    }
  };
  // ?post=traa or ?post=motionblur (WebGPU): three's TRAA (three/addons/tsl/display/TRAANode.js) or
  // motion blur (MotionBlur.js) fed by an MRT velocity output: the crowd's materials write the
  // previous skinned pose into it (spec 21). TRAA wants ?antialias=0 (no MSAA).
  let pipeline = null;
  const post = webgpu ? params.get('post') : null;
  if (post === 'traa' || post === 'motionblur') {
    const tsl = await import('three/tsl');
    const scenePass = tsl.pass(scene, camera);
    scenePass.setMRT(tsl.mrt({ output: tsl.output, velocity: tsl.velocity }));
    const color = scenePass.getTextureNode('output');
    const motion = scenePass.getTextureNode('velocity');
    pipeline = new THREE.RenderPipeline(renderer);
    if (post === 'traa') {
      const { traa } = await import('three/addons/tsl/display/TRAANode.js');
      pipeline.outputNode = traa(color, scenePass.getTextureNode('depth'), motion, camera);
    } else {
      const { motionBlur } = await import('three/addons/tsl/display/MotionBlur.js');
      pipeline.outputNode = motionBlur(color, motion.mul(number('blur', 1)), tsl.int(16));
    }
  }
  const render = () => {
    resize();
    controls.update();
    // Levels of detail (format 1.2): each crowd picks every instance's level for this camera.
    for (const crowd of crowds) crowd.updateLevels(camera);
    if (pipeline) pipeline.render();
    else renderer.render(scene, camera);
    needsRender = false;
  };
  window.addEventListener('resize', () => { needsRender = true; });

  // Frame time: the mean interval between the last 60 animation frames, and the time render() takes.
  const intervals = [];
  let last = performance.now();
  let renderMs = 0;
  const loop = (now) => {
    const dt = (now - last) / 1000;
    last = now;
    intervals.push(dt);
    if (intervals.length > 60) intervals.shift();
    if (playing) setTime(time + dt, dt > 0 ? dt : frameInterval);
    if (needsRender) {
      const start = performance.now();
      render();
      renderMs = 0.9 * renderMs + 0.1 * (performance.now() - start);
    }
    const mean = intervals.reduce((a, b) => a + b, 0) / intervals.length;
    const drawn = crowds.reduce((n, crowd) => n + crowd.count, 0);
    const triangles = crowds.reduce((n, crowd) => n + crowd.trianglesDrawn, 0);
    element('stats').textContent = `frame time: ${(mean * 1000).toFixed(1)} ms (render ${renderMs.toFixed(1)} ms), ${drawn} instances, ${triangles} triangles`;
    requestAnimationFrame(loop);
  };
  setTime(time);

  // WebGLRenderer: a pixel read back finishes a frame; WebGPURenderer: the GPU queue drained (or a
  // pixel read back on its WebGL 2 backend).
  const pixel = new Uint8Array(4);
  const finish = () => {
    if (!webgpu) {
      const gl = renderer.getContext();
      gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, pixel);
    } else if (renderer.backend.isWebGPUBackend) {
      return renderer.backend.device.queue.onSubmittedWorkDone();
    } else {
      const c = renderer.backend.gl;
      c.readPixels(0, 0, 1, 1, c.RGBA, c.UNSIGNED_BYTE, pixel);
    }
    return undefined;
  };
  /** WebGPURenderer: the velocity three's VelocityNode writes to an MRT `velocity` output (what TRAA and
   * motion blur read; the crowd's materials put the previous skinned pose in positionPrevious),
   * rendered into a float32 target (two renders: VelocityNode takes the previous camera from the one
   * before) and read back, in velocity()'s layout. */
  const webgpuVelocity = async () => {
    resize();
    const tsl = await import('three/tsl');
    const scenePass = tsl.pass(scene, camera, { type: THREE.FloatType });
    scenePass.setMRT(tsl.mrt({ output: tsl.output, velocity: tsl.velocity }));
    const velocityPipeline = new THREE.RenderPipeline(renderer);
    velocityPipeline.outputNode = scenePass.getTextureNode('velocity');
    velocityPipeline.render();
    velocityPipeline.render();
    const target = scenePass.renderTarget;
    const index = target.textures.findIndex((texture) => texture.name === 'velocity');
    const { width, height } = target;
    const pixels = await renderer.readRenderTargetPixelsAsync(target, 0, 0, width, height, index);
    velocityPipeline.dispose();
    scenePass.dispose();
    // The WebGL 2 backend reads rows bottom first, WebGPU top first.
    return velocityImage(pixels, width, height, { upward: !renderer.backend.isWebGPUBackend });
  };
  window.vbusd = {
    renderer, scene, camera, controls, crowds, animations: objects.animations, engine, backend,
    setTime, render,
    /** The velocity (motion vectors, spec 21) of the view at the current time and the page's dt: NDC
     * motion since the previous frame, {width, height, rg: row-major from the top row, 2 floats per
     * pixel}. WebGLRenderer: from the crowds' velocity materials (renderVelocity); WebGPURenderer: a
     * Promise of three's MRT velocity output (webgpuVelocity). */
    velocity() {
      if (webgpu) return webgpuVelocity();
      render();
      const size = renderer.getDrawingBufferSize(new THREE.Vector2());
      const target = new THREE.WebGLRenderTarget(size.x, size.y, { type: THREE.FloatType });
      renderVelocity(renderer, scene, camera, target);
      const pixels = new Float32Array(4 * size.x * size.y);
      renderer.readRenderTargetPixels(target, 0, 0, size.x, size.y, pixels);
      target.dispose();
      return velocityImage(pixels, size.x, size.y);
    },
    // instanceCount, probe(instance, t) (with previousPositions for the page's dt), levels(),
    // measureFrames(n): @vbusd/core's page part.
    ...pageApi(crowds,
      (crowd, index, t, options) => (webgpu ? webgpu.probeNodeCrowd(renderer, crowd, index, t, options)
        : probeCrowd(renderer, crowd, index, t, options)),
      (frames = 60) => measureFrames(frames, { step: () => setTime(time + 1 / 60), render, finish }),
      { dt: frameInterval }),
  };
  render();
  requestAnimationFrame(loop);
}

window.vbusdReady = main().catch((error) => { showError(error); throw error; });
