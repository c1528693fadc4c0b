// Types of @vbusd/core/shader-modules (src/shader-modules.js, generated from vbusd's shader source
// by scripts/sync_web.py): the GLSL of `vbusd shader --lang glsl --no-main` as strings.

/** Influences per vertex of the embedded modules (shaderModule rewrites the define for 1..8). */
export const BASE_MAX_INFLUENCES: number;
/** Clips of the embedded modules' clip table (shaderModule rewrites the define). */
export const BASE_MAX_CLIPS: number;
/** "encoding/texelFormat" -> the module with the attribute skin binding. */
export const GLSL_MODULES: Readonly<Record<string, string>>;
/** "encoding/texelFormat" -> the module with the pulled skin binding. */
export const GLSL_PULLED_MODULES: Readonly<Record<string, string>>;
/** Where the layer functions (format 1.2) are inserted into a module. */
export const GLSL_LAYER_MARK: string;
/** encoding -> the layer functions of `vbusd shader --layers`. */
export const GLSL_LAYER_BLOCKS: Readonly<Record<string, string>>;
