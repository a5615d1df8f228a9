"""The HTTP adapter around :mod:`core`: ``app.py`` (``create_app(settings)``), ``main.py`` (the ASGI entry
point), ``cli.py`` (``passive-locator``), ``settings.py``; ``routes/`` (the routers, which reach core only
through the modules below), ``schemas/`` (the models of the contract), ``convert.py`` (schemas <-> core),
``limits.py`` (the cost model), ``planning.py``, ``fixes/`` (the fix pipeline), ``sessions/`` (moving
emitters), ``stores/`` (session stores), ``renderings/`` (CoT, GeoJSON, maps, the TAK feed, reports),
``web/`` (what every request crosses) and ``ops/`` (running the process).
"""
