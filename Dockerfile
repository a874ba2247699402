# fuzzyrisk: the service in a container, beside a robot's software (README: "Beside a ROS 2 robot").
#   docker build -t fuzzyrisk .                            (a fleet's replicas: --build-arg EXTRAS=postgres)
#   docker run -d --name fuzzyrisk --read-only -p 8000:8000 -v fuzzyrisk-data:/data \
#              -e FUZZYRISK_API_KEY=... fuzzyrisk
# Python 3.11 on Debian 12, pinned by tag and by the digest of its multi-platform index: change both together.
ARG PYTHON_IMAGE=python:3.11.14-slim-bookworm@sha256:65a93d69fa75478d554f4ad27c85c1e69fa184956261b4301ebaf6dbb0a3543d

# ---------------------------------------------------------------- build: a virtual environment in /opt/fuzzyrisk
FROM ${PYTHON_IMAGE} AS build
ENV PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PYTHONDONTWRITEBYTECODE=1
# tini (the init of the final image) and strip, from Debian 12 as the pinned base image sees it
RUN apt-get update \
    && apt-get install -y --no-install-recommends tini binutils \
    && rm -rf /var/lib/apt/lists/*
RUN python -m venv /opt/fuzzyrisk
WORKDIR /src
# 1. the dependencies, at the versions of constraints.txt (the lock CI tests with): this layer is rebuilt
#    only when one of these two files changes, not at every change of the code
#    EXTRAS: optional dependencies too, comma-separated: postgres (a fleet on PostgreSQL, README: "Running a fleet")
ARG EXTRAS=""
COPY pyproject.toml constraints.txt ./
RUN python -c "import os, tomllib; p = tomllib.load(open('pyproject.toml', 'rb'))['project']; \
extras = [e for e in os.environ.get('EXTRAS', '').split(',') if e]; \
print('\n'.join(p['dependencies'] + [d for e in extras for d in p['optional-dependencies'][e]]))" \
        > requirements.txt \
    && /opt/fuzzyrisk/bin/pip install --constraint constraints.txt --requirement requirements.txt \
    # what the service never runs: the packages' own test suites, the symbols of LLVM's library (19 MB)
    && find /opt/fuzzyrisk/lib/python3.11/site-packages -depth -type d -name tests -exec rm -rf {} + \
    && strip --strip-unneeded /opt/fuzzyrisk/lib/python3.11/site-packages/llvmlite/binding/libllvmlite.so
# 2. the project itself (compiled to bytecode by pip: a read-only root cannot cache it at run time)
COPY README.md LICENSE ./
COPY app ./app
COPY fuzzyocc ./fuzzyocc
COPY planning ./planning
RUN /opt/fuzzyrisk/bin/pip install --no-deps --constraint constraints.txt . \
    && /opt/fuzzyrisk/bin/pip uninstall --yes pip setuptools

# ---------------------------------------------------------------- the image: Python, the environment, tini
FROM ${PYTHON_IMAGE}
ENV PATH=/opt/fuzzyrisk/bin:$PATH \
    PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    FUZZYRISK_DATA_DIR=/data \
    FUZZYRISK_GRACEFUL_TIMEOUT_S=5
# no pip, setuptools or wheel in the image; a user without a home or a shell; /data theirs
RUN python -m pip uninstall --yes --no-cache-dir pip setuptools wheel \
    && rm -f /usr/local/bin/pip* \
    && useradd --system --uid 10001 --user-group --no-create-home --home-dir /nonexistent \
               --shell /usr/sbin/nologin fuzzyrisk \
    && mkdir /data && chown fuzzyrisk:fuzzyrisk /data
COPY --from=build /usr/bin/tini /usr/bin/tini
COPY --from=build /opt/fuzzyrisk /opt/fuzzyrisk

USER fuzzyrisk
# numba's kernel cache (compiled for this machine's CPU at the first start, loaded at the next ones) and, on
# a read-only root (docker run --read-only), the temporary files go to /data/numba-cache and /data/tmp
WORKDIR /data
VOLUME ["/data"]
EXPOSE 8000

# ready = maps loaded, kernels compiled, planner workers up; the first start on a new volume compiles the
# kernels (about 20 s on 2 cores), hence the start period. No curl in the image: the standard library asks.
HEALTHCHECK --interval=10s --timeout=5s --start-period=120s --retries=3 \
    CMD ["python", "-c", "import os, urllib.request; urllib.request.urlopen('http://127.0.0.1:' + os.environ.get('FUZZYRISK_PORT', '8000') + '/ready', timeout=4)"]

# tini is PID 1: it passes docker stop's SIGTERM to the service and reaps what ends. The service stops within
# docker stop's 10 s: 5 s (FUZZYRISK_GRACEFUL_TIMEOUT_S) for requests in flight, then snapshots, then the
# planner workers (2 s at most); with many large maps give it more: docker run --stop-timeout 60 (and raise
# FUZZYRISK_GRACEFUL_TIMEOUT_S to match).
STOPSIGNAL SIGTERM
ENTRYPOINT ["/usr/bin/tini", "--"]
CMD ["python", "-m", "app", "--host", "0.0.0.0"]
