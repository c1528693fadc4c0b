"""Make the VBUSD_virtual_bones proposal's sample asset, in the glTF-Sample-Assets layout.

spec/extensions/VBUSD_virtual_bones/examples/StadiumCrowd/ holds

* ``glTF-Binary/StadiumCrowd.glb``: ``vbusd export`` of the repository's own stadium crowd
  (samples/stadium_crowd/stadium_crowd_vb.usda: 1,200 spectators of one 18-bone, 202-vertex
  character cheering in a 10 s loop), so the sample's license is the project's;
* ``screenshot/screenshot.png``: that file drawn by ``vbusd view``'s page (three.js and the
  runtime's GLTFLoader plugin) in headless Chromium, at the README picture's camera and time.

The README.md and LICENSE.md beside them are written by hand. Usage (needs what
scripts/install-system-deps.sh installs for the screenshot)::

    python scripts/make_extension_sample.py

tests/test_extension_proposal.py checks that the committed .glb is what the export writes now.
Exit status 2 with one line when the browser is missing (the .glb is still written).
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SOURCE = REPO / "samples" / "stadium_crowd" / "stadium_crowd_vb.usda"
SAMPLE = REPO / "spec" / "extensions" / "VBUSD_virtual_bones" / "examples" / "StadiumCrowd"
MODEL = SAMPLE / "glTF-Binary" / "StadiumCrowd.glb"
SCREENSHOT = SAMPLE / "screenshot" / "screenshot.png"


def export_model(output: Path = MODEL) -> Path:
    """Write the sample's .glb with ``vbusd export`` (deterministic: the same bytes each time).

    Raises:
        RuntimeError: The export failed.
    """
    from vbusd.cli import main as vbusd

    output.parent.mkdir(parents=True, exist_ok=True)
    if vbusd(["export", str(SOURCE), "-o", str(output), "--force"]) != 0:
        raise RuntimeError(f"vbusd export {SOURCE} failed")
    return output


def main(argv=None) -> int:
    """Write the model, then the screenshot.

    Args:
        argv: Command-line arguments (default: ``sys.argv[1:]``).

    Returns:
        0 when both are written, 2 when the browser is missing (one line on stderr).
    """
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model-only", action="store_true", help="write only the .glb")
    args = parser.parse_args(argv)
    export_model()
    if args.model_only:
        return 0
    from vbusd.io.files import atomic_write
    from vbusd.web.browser import unavailable_reason

    reason = unavailable_reason()
    if reason:
        print(f"make_extension_sample: {reason}", file=sys.stderr)
        return 2
    # The README picture's renderer (same page, camera and time), on the exported package.
    spec = importlib.util.spec_from_file_location("make_readme_image", REPO / "scripts" / "make_readme_image.py")
    picture = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(picture)
    data = picture.render_png(MODEL)
    SCREENSHOT.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(SCREENSHOT) as handle:
        handle.write(data)
    print(f"make_extension_sample: wrote {MODEL.relative_to(REPO)} and {SCREENSHOT.relative_to(REPO)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
