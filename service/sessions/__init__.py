"""Sessions (moving emitters): between the session API's models and core's trackers, over a session store.

``observer.py`` is what the session routes call: paper-001 sessions (created with ``observer``), and the
door through which a network session (created with ``stations``) reaches ``network.py``, which
``association.py`` extends for unlabelled bearings (``"association": "auto"``); ``records.py`` is what every
session record gives, whichever kind it holds; ``events.py`` publishes and streams session updates
(server-sent events); ``multi_evaluation.py`` is the multi-emitter evaluation; ``scene_requests.py`` turns
core's simulated scenes into request bodies for the bench and the tests. The models are in
:mod:`service.schemas.sessions`, the renderings in :mod:`service.renderings`. This package imports nothing
itself.
"""
