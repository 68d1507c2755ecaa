# A robot for the container tests: examples/robot_client.py on the client package
# (clients/python), installed from wheels that docker/build stages (no index inside the build).
ARG BASE=loopd-base:bookworm
FROM ${BASE}
RUN apt-get update && apt-get install -y python3 python3-venv && rm -rf /var/lib/apt/lists/*
COPY wheels /wheels
RUN python3 -m venv /opt/robot && /opt/robot/bin/pip install --quiet --no-index --find-links /wheels loopd-client \
    && rm -rf /wheels && useradd --system --uid 10002 robot
COPY robot_client.py /usr/local/bin/robot_client.py
USER robot
ENTRYPOINT ["/opt/robot/bin/python", "/usr/local/bin/robot_client.py"]
