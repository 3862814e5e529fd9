"""`warpmpm make-cine` as a script (see `python examples/make_cine.py --help`).

    python examples/make_cine.py --out runs/cine --frames 8
    python examples/track.py --image PLAN --labels LABELS --preset P --cine runs/cine/cine --out runs/track
    python examples/evaluate_track.py --track runs/track --truth runs/cine/truth --json eval.json
"""

import sys


from warpmpm.cli import main

if __name__ == "__main__":
    raise SystemExit(main(["make-cine", *sys.argv[1:]]))
