"""The S3 store the tests use: CI's moto server on loopback (.ci/services starts it), or any S3 endpoint named
by the environment (NAVSIM_LB_TEST_S3_BUCKET with the standard AWS_* variables). It must answer: a test that
needs it fails, never skips, when it does not."""

from __future__ import annotations

import os
import socket
import uuid

import boto3
import botocore.exceptions

from server.object_store import S3Store

BUCKET = os.environ.get("NAVSIM_LB_TEST_S3_BUCKET", "navsim-lb-test")
CI_S3_ENDPOINT = "http://127.0.0.1:9000"
# CI's moto server takes any keys; a real endpoint comes with its own.
for _variable, _default in (
    ("AWS_ENDPOINT_URL", CI_S3_ENDPOINT),
    ("AWS_ACCESS_KEY_ID", "test"),
    ("AWS_SECRET_ACCESS_KEY", "test"),
    ("AWS_DEFAULT_REGION", "us-east-1"),
):
    os.environ.setdefault(_variable, _default)


def port_answers(port: int) -> bool:
    """Whether a server accepts connections on the loopback port (an S3 server starting)."""
    try:
        socket.create_connection(("127.0.0.1", port), timeout=1).close()
        return True
    except OSError:
        return False


def make_bucket(name: str = BUCKET) -> None:
    """Create the bucket unless it exists; fail with the fix when the S3 endpoint does not answer."""
    client = boto3.client("s3")
    try:
        client.head_bucket(Bucket=name)
    except botocore.exceptions.EndpointConnectionError as error:
        raise AssertionError(
            f"no S3 server answers at {os.environ['AWS_ENDPOINT_URL']} ({error}): run .ci/services"
        ) from None
    except botocore.exceptions.ClientError:
        client.create_bucket(Bucket=name)


def fresh_s3_store() -> S3Store:
    """Return an empty store: a new prefix in the test bucket."""
    make_bucket()
    return S3Store(BUCKET, f"test-{uuid.uuid4().hex}")
