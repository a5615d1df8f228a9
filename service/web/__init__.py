"""What every request crosses on its way in and out, whichever route serves it.

``middleware.py`` (request ids, limits, who is asking, one log line), ``headers.py`` (the header fields, read
once), ``auth.py`` (bearer keys), ``deps.py`` (the routers' shared dependencies), ``problems.py``
(problem+json: the one place errors become responses), ``responses.py`` (orjson bodies), ``watch.py``
(long work watched for its deadline, its client and the server's shutdown), ``openapi.py`` (the OpenAPI
document completed with every error) and ``browsers.py`` (the docs served locally, CORS). This package
imports nothing itself.
"""
