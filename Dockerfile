# cosim in a container: `docker build -t cosim .` then
#   docker run --rm -v "$PWD/out:/app/out" cosim run scenarios/town_rural_night.yaml
#   docker run --rm -v "$PWD/out:/out" cosim batch sweeps/airv2x_like.yaml --out /out --shard 3/16
FROM python:3.11-slim

# Open3D's system libraries (the same list the Makefile installs).
RUN apt-get update \
 && apt-get install -y --no-install-recommends libusb-1.0-0 libgl1 libegl1 libgomp1 \
 && rm -rf /var/lib/apt/lists/*

WORKDIR /app
COPY pyproject.toml README.md ./
COPY cosim ./cosim
COPY sensors ./sensors
COPY exporters ./exporters
RUN pip install --no-cache-dir .
COPY scenarios ./scenarios
COPY sweeps ./sweeps

ENV COSIM_SCENARIO_PATH=/app/scenarios \
    COSIM_SWEEP_PATH=/app/sweeps \
    PYTHONUNBUFFERED=1
ENTRYPOINT ["cosim"]
CMD ["--help"]
