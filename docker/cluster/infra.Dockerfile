# The cluster's infrastructure on the debootstrap base (docker/base-image): one image for the etcd,
# PostgreSQL + Patroni and HAProxy containers of docker/cluster/compose.yaml. PostgreSQL 15, etcd
# and HAProxy are Debian's; Patroni is PyPI's 4.1.5 (newer than Debian's 3.0.2, which has a known
# demotion bug with etcd 3.4), from wheels that docker/cluster/build stages (no index in the build).
ARG BASE=loopd-base:bookworm
FROM ${BASE}
RUN apt-get update && apt-get install -y postgresql-15 etcd-server etcd-client haproxy python3 python3-venv \
        curl iproute2 procps \
    && rm -rf /var/lib/apt/lists/* \
    && mkdir -p /data/pg /data/etcd && chown postgres:postgres /data/pg
COPY wheels /wheels
RUN python3 -m venv /opt/patroni \
    && /opt/patroni/bin/pip install --quiet --no-index --find-links /wheels "patroni[etcd3]" psycopg2-binary \
    && rm -rf /wheels && ln -s /opt/patroni/bin/patroni /opt/patroni/bin/patronictl /usr/local/bin/
COPY patroni.yml haproxy.cfg post-bootstrap /etc/loopd-cluster/
ENV PATH=/usr/lib/postgresql/15/bin:$PATH LANG=C.UTF-8
