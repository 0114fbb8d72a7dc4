# Tether's server image: Debian 12, built with scripts/setup.sh (the same packages and preset as a fresh machine).
#   docker build -t tether:dev .
#   docker run --rm -p 8080:8080 tether:dev serve /opt/tether/models/demo/smolvla-demo --host 0.0.0.0 --port 8080
# The runtime stage installs only the Debian packages the binary links against (found with ldd and dpkg -S in the
# build stage), not the compilers and -dev packages.
FROM debian:12 AS build
RUN apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
      ca-certificates sudo && rm -rf /var/lib/apt/lists/*
WORKDIR /src
COPY . .
# The portable build (no -march=native): one image serves every x86-64 CPU; kernels dispatch at run time.
RUN scripts/setup.sh release tether
# The packages owning each shared library the binary needs (merged /usr: a library may be recorded under /lib).
RUN ldd build/release/tether | awk '/=> \// { print $3 }' | while read -r lib; do \
      real="$(readlink -f "$lib")"; \
      for p in "$lib" "$real" "${lib#/usr}" "${real#/usr}" "/usr$lib" "/usr$real"; do \
        dpkg -S "$p" 2>/dev/null && break; \
      done; \
    done | cut -d: -f1 | sort -u > /runtime-packages.txt && cat /runtime-packages.txt

FROM debian:12
COPY --from=build /runtime-packages.txt /tmp/runtime-packages.txt
RUN apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
      ca-certificates $(cat /tmp/runtime-packages.txt) && rm -rf /var/lib/apt/lists/* /tmp/runtime-packages.txt
COPY --from=build /src/build/release/tether /opt/tether/bin/tether
# Registry, embodiment presets and the bundled demo policy (data files the CLI reads from TETHER_DATA_DIR).
COPY --from=build /src/models /opt/tether/models
RUN useradd --system --uid 10001 --home-dir /var/lib/tether --create-home tether
ENV PATH=/opt/tether/bin:$PATH \
    TETHER_DATA_DIR=/opt/tether/models \
    TETHER_REGISTRY=/opt/tether/models/registry.json \
    TETHER_CACHE=/var/lib/tether/cache \
    HF_HOME=/var/lib/tether/cache/huggingface
USER tether
WORKDIR /var/lib/tether
EXPOSE 8080
ENTRYPOINT ["tether"]
CMD ["serve", "/opt/tether/models/demo/smolvla-demo", "--host", "0.0.0.0", "--port", "8080"]
