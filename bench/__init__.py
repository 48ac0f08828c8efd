"""Benchmarks, kept out of the tests: ``cae-lcd bench`` (``bench.run`` and the section modules ``common``,
``speed``, ``methods``, ``index_scaling``) and standalone studies run as ``python -m bench.<name>``
(``choose_policy``, ``speed_ablation``, ``retrieval_margin``).

Layer: above ``evaluation``, below ``cli``; nothing here imports ``cli``.
"""
