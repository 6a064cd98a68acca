"""``fit --batch``'s local Dask cluster is private: TLS with mutual authentication on every
listener, no HTTP (dashboard, info, JSON) port, nothing another local user can connect to;
bad ``--workers`` and ``--scheduler`` are refused at once instead of hanging."""

import socket
import ssl
import time

import numpy as np
import psutil
import pytest

import gonio.models as gm
from gonio.fitting.batch.dask_batch import (MAX_WORKERS, _close_http, check_scheduler_address, check_workers, fit_batch,
                                  fit_serial, local_cluster, local_security)

from _simdata import simulate


def _listening_ports():
    me = psutil.Process()
    ports = set()
    for proc in [me, *me.children(recursive=True)]:
        try:
            for conn in proc.net_connections(kind="inet"):
                if conn.status == psutil.CONN_LISTEN:
                    ports.add(conn.laddr.port)
        except psutil.Error:
            continue
    return ports


def _answers_plain_http(port) -> bool:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=3) as s:
            s.sendall(b"GET /info/main/workers.html HTTP/1.0\r\nHost: x\r\n\r\n")
            s.settimeout(3)
            data = s.recv(64)
    except OSError:
        return False
    return data.startswith(b"HTTP/")


def _tls_without_certificate_accepted(port) -> bool:
    """An attacker's TLS client (no client certificate, trusting anything): does the server talk?"""
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    ctx.check_hostname = False
    ctx.verify_mode = ssl.CERT_NONE
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=3) as raw:
            with ctx.wrap_socket(raw) as s:
                s.settimeout(3)
                s.sendall(b"\x00" * 8)
                data = s.recv(64)           # TLS 1.3 reports a missing client certificate here
                return len(data) > 0
    except (OSError, ssl.SSLError):
        return False


@pytest.mark.slow
def test_local_cluster_listens_only_with_mutual_tls():
    from distributed import Client

    before = _listening_ports()
    cluster = local_cluster(1)
    try:
        client = Client(cluster, security=cluster.security)
        try:
            _close_http(client, keep_scheduler=False)
            assert cluster.scheduler_address.startswith(("tls://", "inproc://")), cluster.scheduler_address
            if cluster.scheduler_address.startswith("inproc://"):
                assert _listening_ports() - before == set()
                return
            ports = _listening_ports() - before
            assert ports, "the cluster should listen on TLS ports"
            assert 8787 not in ports
            for port in ports:
                assert not _answers_plain_http(port), f"port {port} serves HTTP without authentication"
                assert not _tls_without_certificate_accepted(port), f"port {port} accepts TLS without a certificate"
            # a dask client without the run's certificate gets nowhere: plain TCP, or TLS with another key
            plain = cluster.scheduler_address.replace("tls://", "tcp://")
            with pytest.raises((OSError, TimeoutError)):
                Client(plain, timeout="3s")
            other = local_security()
            with pytest.raises((OSError, TimeoutError)):
                Client(cluster.scheduler_address, security=other, timeout="3s")
            assert client.submit(sum, [1, 2], pure=False).result() == 3
        finally:
            client.close()
    finally:
        cluster.close()


def test_workers_are_validated_before_a_cluster_starts():
    assert check_workers(1) == 1 and check_workers(MAX_WORKERS) == MAX_WORKERS
    for bad in (0, -1, MAX_WORKERS + 1, 10 ** 9, 1.5, True, "2"):
        with pytest.raises(ValueError, match="--workers"):
            check_workers(bad)
    model = gm.get("diffuse")
    data = [simulate(model, {"reflectance": np.array([0.5, 0.4, 0.3])}, np.random.default_rng(0), n=20)]
    t0 = time.monotonic()
    with pytest.raises(ValueError, match="--workers"):
        fit_batch(data, model, n_workers=0)        # hung forever on 15e620e
    assert time.monotonic() - t0 < 5


def test_scheduler_address_is_validated():
    for good in ("tls://10.0.0.5:8786", "tcp://127.0.0.1:8786", "localhost:8786", "tls://[::1]:8786"):
        assert check_scheduler_address(good) == good
    for bad in ("not a url", "", "tcp://", "tcp://host", "http://host:80", "tcp://host:0", "tcp://host:99999",
                "tcp://host:8786; rm -rf /", "\x00:1"):
        with pytest.raises(ValueError, match="--scheduler"):
            check_scheduler_address(bad)


@pytest.mark.slow
def test_private_cluster_still_equals_serial():
    model = gm.get("diffuse")
    truth = {"reflectance": np.array([0.5, 0.35, 0.2])}
    data = [simulate(model, truth, np.random.default_rng(s), n=60) for s in range(3)]
    serial = fit_serial(data, model, rng_seed=4)
    batch = fit_batch(data, model, n_workers=2, rng_seed=4)
    for a, b in zip(batch, serial):
        np.testing.assert_allclose(a.x, b.x, rtol=1e-9, atol=1e-12)


@pytest.mark.slow
def test_a_tls_scheduler_without_certificates_is_one_connection_error():
    model = gm.get("diffuse")
    data = [simulate(model, {"reflectance": np.array([0.5, 0.4, 0.3])}, np.random.default_rng(0), n=20)]
    cluster = local_cluster(1)
    try:
        with pytest.raises(ConnectionError, match="certificates"):
            fit_batch(data, model, scheduler=cluster.scheduler_address)     # TypeError on 15e620e
    finally:
        cluster.close()


def test_dashboard_address_is_validated():
    from gonio.fitting.batch.dask_batch import check_dashboard_address

    assert check_dashboard_address("127.0.0.1:8787") == "127.0.0.1:8787"
    for bad in ("x y", "tcp://127.0.0.1:8787", ":::", "host:70000"):
        with pytest.raises(ValueError, match="--dashboard"):
            check_dashboard_address(bad)
