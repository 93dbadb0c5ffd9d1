"""Beyond the paper: the stages of chapters 09-12, one module per chapter's subject.

* :mod:`~flowmod.extensions.blind_spots` (chapter 09): what flow cannot see, the geometry of
  a vehicle's motion seen from the camera;
* :mod:`~flowmod.extensions.context` and :mod:`~flowmod.extensions.inputs` (chapter 10,
  ``extension_inputs``): the classifier on other inputs than the raw flow;
* :mod:`~flowmod.extensions.wide` (chapter 11, ``wide_methods``): trained on all distances;
* :mod:`~flowmod.extensions.selfflow` (chapter 12, ``selfflow_modes``): FastFlowNet trained
  here from scratch.

Their models are trained by ``make book`` for the profile's chains (``extension_build``,
``selfflow_build``); ``make extensions`` and ``make selfflow`` add the rest of the matrix.
"""
