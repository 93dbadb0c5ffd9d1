"""The chapters' backends: one module per notebook (``chNN_<name>`` for ``NN_<name>.ipynb``).

A chapter module holds what its notebook shows: tables, headlines, notes and the numbers it
glues, all read from the published artefacts of the stages (:mod:`flowmod.pipeline`).
Stage modules keep the algorithms and the node building; a notebook calls
``pipeline.build(P, [chapter])`` and then its chapter module. :mod:`~flowmod.chapters.common`
holds what several chapters read.
"""
