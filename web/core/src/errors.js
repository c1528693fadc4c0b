// The one error class of vbusd's web runtimes: bad data handed to a runtime, or a browser or GPU
// that cannot run it, in one clear line.

/** An error in the data handed to the runtime, or a browser that cannot run it. */
export class VirtualBonesError extends Error {
  constructor(message) {
    super(`vbusd: ${message}`);
    this.name = 'VirtualBonesError';
  }
}
