// The web core's blend spaces and events (web/core/src/motion.js) on the queries of a JSON file: the
// JavaScript side of tests/test_web_motion.py, which compares it with vbusd.format.motion.
// Usage: node core_motion.mjs QUERIES.json -> {weights: [...], triangles: [...], phases: [...], events: [...], crowd: [...]}
import fs from 'node:fs';
import {
  blendWeights, crossedMarkers, crowdEvents, layerWeights, phaseTimes, triangulate,
} from '../../web/core/src/motion.js';

const q = JSON.parse(fs.readFileSync(process.argv[2], 'utf8'));
const out = {
  weights: q.weights.map(({ space, x, y }) => blendWeights(space, x, y)),
  layers: q.weights.map(({ space, x, y }) => layerWeights(blendWeights(space, x, y))),
  triangles: q.triangles.map((points) => triangulate(points)),
  phases: q.phases.map(({ space, durations, markers, phase }) => phaseTimes(space, durations, markers, phase)),
  events: q.events.map(({ markers, clip, duration, loop, t0, t1 }) => crossedMarkers(markers, clip, duration, loop, t0, t1)),
  crowd: crowdEvents(q.crowd.markers, q.crowd.clips, q.crowd.clip, q.crowd.timeOffset, q.crowd.playbackRate, q.crowd.t0, q.crowd.t1),
};
process.stdout.write(JSON.stringify(out));
