"""The fleet server's library: several robots send keyframes, the server finds where two of them saw the same place,
estimates the similarity transform between their maps and keeps one global pose graph (issue 12).

- ``sim3``: the similarity transform ``Sim3``, Umeyama's closed form, RANSAC with a robust refinement.
- ``graph``: the global pose graph in gtsam (``Similarity3`` nodes, odometry, loop and overlap edges).
- ``store``: robots, hashed tokens, keyframe acknowledgements, edges and transforms (``FleetStore``, SQLite).
- ``overlap``: the "n consecutive matching keyframes" rule and the 3D-3D correspondences of a matched pair.
- ``recognition``: the ``detect`` pipeline on every robot's keyframes (one ``LoopDetector`` per robot, one shared
  encoder), cross-robot search and verification, loop and overlap edges.
- ``optimizer``: the pose graph re-solved in a worker thread; reads get the latest solution.
- ``service``: robots, tokens, keyframes, recognition and the graph over a store, without HTTP; ``server``: the
  FastAPI app (``create_app``); ``client``: a small httpx client; ``runner``: the app on uvicorn in a thread.
- ``demo``: two robots streaming KITTI to a server on loopback (``cae-lcd fleet-demo``); ``plots``: trajectories
  before and after the merge.

Layer: uses ``core``, ``verify`` and ``retrieval``; never ``evaluation`` or ``bench``; the CLI sits on top.
"""

from .sim3 import Sim3, ransac_sim3, umeyama

__all__ = ["Sim3", "umeyama", "ransac_sim3"]
