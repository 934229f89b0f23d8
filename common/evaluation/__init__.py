"""Evaluation and benchmarks. May import every other package of ``common``.

``scoring`` (errors, NEES, collected results), ``report`` (tables and figures), ``cli`` (the
``needletrack eval`` command), ``pipeline_graph`` (the graph an evaluation runs); the
``needletrack bench`` benchmarks: ``graph_bench``, ``transport_bench``, ``sim_bench``,
``detector_bench``, ``refine_bench``, ``geometry_bench``.
"""
