# fuzzyrisk: the service in a container, beside a robot's software (docs/operations.md, docs/ros2.md).
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
#    EXTRAS: optional dependencies too, comma-separated: postgres (a fleet on PostgreSQL, docs/fleet.md)
ARG EXTRAS=""
COPY pyproject.toml constraints.txt ./
RUN python -c "import os, tomllib; p = tomllib.load(open('pyproject.toml', 'rb'))['project']; \
extras = [e for e in os.environ.get('EXTRAS', '').split(',') if e]; \
print('\n'.join(p['dependencies'] + [d for e in extras for d in p['optional-dependencies'][e]]))" \
        > requirements.txt \
    && /opt/fuzzyrisk/bin/pip install --constraint constraints.txt --requirement requirements.txt
#    then out of the environment, before the image copies it, what the service never loads (an image
#    of at most 500 MB: 478 MB with the real slim base as ../shared/tools/container-check reckons it, 412 MB before
#    scipy came back). scipy, for the 3-D rotations, is 143 MiB installed (du -sh of site-packages: scipy 113M,
#    scipy.libs 30M), 101 MiB after the trims below, 64 MiB once its subpackages the service never imports are out;
#    tests/e2e/test_container.py checks that the service loads none of what goes:
#    - the packages' test suites, typing stubs, Cython declarations and static libraries;
#    - scipy's subpackages other than spatial and what it imports (linalg, sparse, special, constants, _lib): 37 MiB;
#    - zstandard's cffi backend (CPython loads the C one), apsw's SQLite extensions and shell tools, numpy's
#      distutils, C headers and SIMD test module, numba's CUDA target;
#    - pillow's AVIF, WebP, FreeType and LittleCMS modules and the libraries only they use: the service writes
#      PNG only, and pillow runs without them (those formats then report themselves unsupported): 9 MB;
#    - the symbol tables of the shared libraries (70 MB, LLVM's 19 of them), except where strip would break a
#      library that auditwheel's patchelf rewrote (the loader refuses it: "ELF load command address/offset not
#      page-aligned"): a stripped copy replaces a library only if ldd still loads it.
RUN cd /opt/fuzzyrisk/lib/python3.11/site-packages \
    && find . -depth -type d -name tests -exec rm -rf {} + \
    && find . -type f \( -name '*.pyi' -o -name '*.pxd' -o -name '*.pyx' -o -name '*.pxi' -o -name '*.a' \) -delete \
    && rm -rf zstandard/_cffi.*.so zstandard/backend_cffi.py zstandard/__pycache__/backend_cffi.* \
              apsw/sqlite_extra_binaries numpy/distutils numpy/_pyinstaller numpy/doc numpy/_core/include \
              numpy/_core/_simd.*.so numba/cuda \
    && rm -rf scipy/optimize scipy/stats scipy/signal scipy/io scipy/interpolate scipy/integrate scipy/ndimage \
              scipy/fft scipy/fftpack scipy/odr scipy/misc scipy/datasets scipy/cluster scipy/differentiate \
    && rm -rf PIL/_avif.*.so PIL/_webp.*.so PIL/_imagingft.*.so PIL/_imagingcms.*.so pillow.libs/libavif-* \
              pillow.libs/libwebp* pillow.libs/libsharpyuv-* pillow.libs/libfreetype-* pillow.libs/libharfbuzz-* \
              pillow.libs/libbrotli* pillow.libs/libpng16-* pillow.libs/liblcms2-* \
    && find . -type f \( -name '*.so' -o -name '*.so.*' \) -exec sh -c 'for f; do \
           strip --strip-unneeded -o "$f.stripped" "$f" && ldd "$f.stripped" >/dev/null 2>&1 \
           && mv "$f.stripped" "$f" || rm -f "$f.stripped"; done' sh {} +
# 2. the project itself (compiled to bytecode by pip: a read-only root cannot cache it at run time)
COPY README.md LICENSE ./
COPY app ./app
COPY fuzzyocc ./fuzzyocc
COPY planning ./planning
COPY fuzzyrisk_bridge ./fuzzyrisk_bridge
RUN /opt/fuzzyrisk/bin/pip install --no-deps --constraint constraints.txt . \
    && /opt/fuzzyrisk/bin/pip uninstall --yes pip setuptools \
    # a trim that went too far (a new version of a dependency that needs what step 1 removes) fails the build;
    # planning.query compiles kernels as it is imported: their cache goes to /tmp, which the image does not copy
    && NUMBA_CACHE_DIR=/tmp/numba-cache /opt/fuzzyrisk/bin/python -I -c \
           "import app.api.factory, app.plans.worker, app.cli.import_bag, planning.query"

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
