"""moto's S3 server with HTTP/1.1 keep-alive, for the benchmarks' own store: `python keepalive_s3.py PORT`.

`python -m moto.server` serves through werkzeug's development server, which closes the connection after every
response, so each GET of a worker opens a TCP connection: 0.3 of the 1.2-1.3 CPU-ms a 120 kB GET costs the
client (botocore) here, and a thread per request to moto. AWS S3, MinIO and Ceph keep connections alive (the
client's pool reuses them), so the benchmark serves the same moto application through uvicorn's WSGI
interface, which keeps them alive too: what a worker pays per object is then what it pays a real store.
"""

from __future__ import annotations

import sys

import uvicorn
from moto.moto_server.werkzeug_app import DomainDispatcherApplication, create_backend_app

if __name__ == "__main__":
    application = DomainDispatcherApplication(create_backend_app)
    uvicorn.run(application, host="127.0.0.1", port=int(sys.argv[1]), interface="wsgi", log_level="warning")
