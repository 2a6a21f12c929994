# detcal: the calibration service, CPU only.
#   docker build -t detcal .
#   docker run -p 8000:8000 -v detcal-data:/data -e DETCAL_ADMIN_TOKEN=... detcal
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    DETCAL_DATA_DIR=/data \
    DETCAL_HOST=0.0.0.0 \
    DETCAL_PORT=8000

WORKDIR /opt/detcal

# Versions from the lock (torch pinned there too); the CPU index provides the CPU-only torch wheel.
COPY pyproject.toml requirements.lock README.md ./
COPY app ./app
COPY calibrators ./calibrators
COPY detectors ./detectors
RUN pip install --extra-index-url https://download.pytorch.org/whl/cpu \
        -c requirements.lock ".[detectors,service]" \
    && useradd --create-home --uid 10001 detcal \
    && mkdir -p /data && chown detcal:detcal /data

USER detcal
VOLUME /data
EXPOSE 8000

HEALTHCHECK --interval=30s --timeout=5s --start-period=120s --retries=3 \
    CMD python -c "import urllib.request, sys; sys.exit(0 if urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=4).status == 200 else 1)"

CMD ["detcal", "serve", "--host", "0.0.0.0", "--bootstrap"]
