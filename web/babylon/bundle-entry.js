// The Babylon.js modules `vbusd view --engine babylon` and docs/engines.md's example import, bundled
// once by esbuild (`npm run bundle` in web/babylon) into dist/babylon.bundle.js: @babylonjs/core's
// ES modules are ~1,800 files, too many to ship. scripts/sync_web.py copies the bundle, with
// Babylon's licence, to web/vendor/babylon-<version>/ (committed once; the wheel's copy is made at
// build time); the page's import map points '@babylonjs/core' and '@babylonjs/loaders/glTF/2.0' at
// it. Not part of the @vbusd/babylon npm package, which imports Babylon.js by name.
export {
  Engine, Scene, Mesh, VertexData, Matrix, Vector3, Color3, Color4, StandardMaterial, PBRMaterial,
  MaterialPluginBase, ShadowDepthWrapper, ShadowGenerator, DirectionalLight, HemisphericLight,
  ArcRotateCamera, MeshBuilder, RawTexture, Constants, SceneLoader, LoadAssetContainerAsync,
  ImportMeshAsync, BakedVertexAnimationManager, VertexAnimationBaker, AnimationRange, Quaternion,
  Tools, VertexBuffer, EngineStore, Camera, Frustum, BoundingSphere,
} from '@babylonjs/core';
export { GLTFLoader } from '@babylonjs/loaders/glTF/2.0/index.js';
