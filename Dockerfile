# fuzzyrisk: the service in a container, beside a robot's software.
#   docker build -t fuzzyrisk .
#   docker run -d -p 8000:8000 -v fuzzyrisk-data:/data -e FUZZYRISK_API_KEY=... fuzzyrisk
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    FUZZYRISK_DATA_DIR=/data \
    NUMBA_CACHE_DIR=/var/cache/numba

# install the project with pip, as `python3 dev.py serve` does (editable there, a plain install here)
WORKDIR /build
COPY pyproject.toml README.md ./
COPY app ./app
COPY fuzzyocc ./fuzzyocc
COPY planning ./planning
RUN pip install . \
    && rm -rf /build

# compile the numba kernels into the image, so a new container's first scan does not wait for them;
# the cache stays writable for the service's user
RUN python -m app.warmup \
    && useradd --system --uid 10001 --user-group --no-create-home fuzzyrisk \
    && mkdir -p /data \
    && chown -R fuzzyrisk:fuzzyrisk /data "$NUMBA_CACHE_DIR"

USER fuzzyrisk
WORKDIR /data
VOLUME ["/data"]
EXPOSE 8000

# no curl in the image: ask /health with the standard library
HEALTHCHECK --interval=30s --timeout=5s --start-period=60s --retries=3 \
    CMD ["python", "-c", "import os, urllib.request; urllib.request.urlopen('http://127.0.0.1:' + os.environ.get('FUZZYRISK_PORT', '8000') + '/health', timeout=4)"]

# exec form: python is PID 1 and gets SIGTERM (docker stop) for a graceful shutdown
CMD ["python", "-m", "app", "--host", "0.0.0.0"]
