# cosim in a container (README, "Containers"). Two ways to build:
#   with a registry:    docker build -t cosim .            (base python:3.11-slim, packages from PyPI)
#   offline:            make image BASE=cosim-base:bookworm (wheels from wheelhouse/, base from docker/base.sh)
# and run it with the output on a bind mount:
#   docker run --rm -u "$(id -u):$(id -g)" -v "$PWD/out:/out" cosim run scenarios/default.yaml --out /out
#   docker run --rm -u "$(id -u):$(id -g)" -v "$PWD/out:/out" cosim batch smoke --out /out --shard 0/3
ARG BASE=python:3.11-slim

# ---- deps stage: a virtual environment in /opt/cosim with every dependency; wheels never reach the final image.
# It changes only with the wheelhouse, so a change to cosim's sources rebuilds the small layers below, not
# this one (2.5 GB: copying it into a new layer took about a minute of the daemon's CPU per build).
FROM ${BASE} AS deps
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
RUN python3 -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' \
 && python3 -m venv /opt/cosim
# wheelhouse/ (tracked, empty but for its .gitignore) holds the dependency wheels of `make wheelhouse`;
# when it has any, everything installs from it with --no-index (no network), else from PyPI.
COPY wheelhouse/ /tmp/wheelhouse/
RUN if ls /tmp/wheelhouse/*.whl >/dev/null 2>&1; then \
      /opt/cosim/bin/pip install --no-index --find-links /tmp/wheelhouse /tmp/wheelhouse/*.whl; \
    fi \
 && touch /tmp/deps-done

# ---- build stage: cosim on top; /overlay gets every file the install wrote (without a wheelhouse, that is
# the dependencies too)
FROM deps AS build
# EXTRAS: optional dependencies, e.g. --build-arg EXTRAS=ray for `cosim batch --backend ray`.
ARG EXTRAS=
COPY pyproject.toml README.md /src/
COPY cosim /src/cosim
COPY sensors /src/sensors
COPY exporters /src/exporters
RUN spec="/src${EXTRAS:+[$EXTRAS]}"; \
    if ls /tmp/wheelhouse/*.whl >/dev/null 2>&1; then \
      /opt/cosim/bin/pip install --no-index --find-links /tmp/wheelhouse "$spec"; \
    else \
      /opt/cosim/bin/pip install "$spec"; \
    fi \
 && mkdir /overlay \
 && cd /opt/cosim && find . -newer /tmp/deps-done ! -type d -exec cp -a --parents -t /overlay {} +

# ---- final image: the base, Open3D's system libraries, the environment, scenarios and sweeps
FROM ${BASE}
# The Open3D and SUMO wheels link against these (the Makefile's SYSTEM_LIBS): docker/base.sh's base
# has them, python:3.11-slim gets them from apt.
RUN missing=; \
    for lib in libusb-1.0.so.0 libGL.so.1 libEGL.so.1 libgomp.so.1 libatomic.so.1 libXrender.so.1; do \
      ldconfig -p | grep -q "$lib" || missing=1; \
    done; \
    if [ -n "$missing" ]; then \
      apt-get update \
      && apt-get install -y --no-install-recommends libusb-1.0-0 libgl1 libegl1 libgomp1 libatomic1 libxrender1 \
      && rm -rf /var/lib/apt/lists/*; \
    fi
COPY --from=deps /opt/cosim /opt/cosim
COPY --from=build /overlay/ /opt/cosim/
RUN /opt/cosim/bin/pip uninstall -y -q pip setuptools wheel
WORKDIR /app
COPY scenarios ./scenarios
COPY sweeps ./sweeps
ENV PATH=/opt/cosim/bin:$PATH \
    COSIM_SCENARIO_PATH=/app/scenarios \
    COSIM_SWEEP_PATH=/app/sweeps \
    PYTHONUNBUFFERED=1 \
    HOME=/tmp
ENTRYPOINT ["cosim"]
CMD ["--help"]
