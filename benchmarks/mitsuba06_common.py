"""What the three parts of the Mitsuba 0.6 contestant share (mitsuba06.py)."""

from pathlib import Path

ENV_VAR = 'MITSUBA06_DIST'      # a dist/ folder (or the `mitsuba` binary in it) when --mitsuba06 is not given
RR_DEPTH = 5                    # Mitsuba 3's default rr_depth (also bdpt's); 0.6's default is 5 as well
KEEP_SYMBOLIC = ('integrator', 'spp', 'seed')   # parameters the converted file leaves to `-D` on the command line
REPO = Path(__file__).resolve().parents[1]


class Mitsuba06Error(RuntimeError):
    """Mitsuba 0.6 cannot be built, a scene cannot be converted, or a render failed."""

