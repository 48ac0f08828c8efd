"""Finding candidates and remembering keyframes: the code index, the HDF5 keyframe database, the detector that
chains gate -> encode -> search -> verify -> insert, sequence readers, and the ``cae-lcd`` command line."""

from .database import KeyframeDatabase, KeyframeRecord
from .detector import Candidate, FrameResult, LoopDetector, resolve_conf
from .index import INDEXES, KeyframeIndex, create_index
from .sequences import Sequence, open_sequence
from . import baselines  # noqa: F401,E402  (registers the baseline global descriptors: thumbnail, bovw)
from . import mild  # noqa: F401,E402  (registers MILD's descriptor: mild)

__all__ = ["LoopDetector", "FrameResult", "Candidate", "resolve_conf", "KeyframeDatabase", "KeyframeRecord",
           "KeyframeIndex", "INDEXES", "create_index", "Sequence", "open_sequence"]
