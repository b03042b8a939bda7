# One image for every Python service of the deployment: `ldm core`, `laas worker`,
# `laas simulate` (see docker-compose.yml). No entrypoint: the
# command is the program.
#
#   docker build -t laas .
#   docker run --rm laas laas worker --help
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

WORKDIR /app

# The project, installed from the repository's own files (README.md is the package's
# long description; the [d] glob keeps the build going while it is absent).
COPY pyproject.toml README.m[d] ./
COPY src ./src
RUN pip install . && rm -rf build src/*.egg-info

COPY maps ./maps
# The containers' health checks and the compose simulator (one account per road user).
COPY deploy/healthcheck.py ./deploy/

# The bundled maps (laas.map.bundled looks in $LAAS_MAPS first), and numba's cache of
# the engine's compiled arithmetic (laas.engine.jit), which site-packages, owned by root,
# cannot hold for the user the image runs as.
ENV LAAS_MAPS=/app/maps \
    NUMBA_CACHE_DIR=/app/numba-cache

RUN useradd --system --uid 10001 --no-create-home --shell /usr/sbin/nologin laas
# The compiled arithmetic built once, here, so no container compiles it (some seconds)
# before its worker's first fix; the cache stays writable by the user.
RUN python -m laas.engine.warm && chown -R laas /app/numba-cache
USER laas

ENV LAAS_MAP=/app/maps/messe-hamburg.geojson
CMD ["laas", "--help"]
