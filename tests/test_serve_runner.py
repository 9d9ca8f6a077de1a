"""The servers' listening socket: the connections asyncio accepts on it get TCP_NODELAY (asyncio sets
it only on sockets whose proto is IPPROTO_TCP; without it every reply uvicorn writes in two parts
waited for the client's delayed ACK, about 40 ms a request on loopback)."""

from __future__ import annotations

import asyncio
import socket

from brave6d.serve.runner import listening_socket


def test_accepted_connections_have_nodelay() -> None:
    seen: list[int] = []

    class Record(asyncio.Protocol):
        def connection_made(self, transport: asyncio.BaseTransport) -> None:
            seen.append(transport.get_extra_info("socket").getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY))
            transport.close()

    async def main() -> None:
        sock = listening_socket("127.0.0.1", 0)
        server = await asyncio.get_running_loop().create_server(Record, sock=sock)
        async with server:
            _, writer = await asyncio.open_connection("127.0.0.1", sock.getsockname()[1])
            for _ in range(200):
                if seen:
                    break
                await asyncio.sleep(0.01)
            writer.close()

    asyncio.run(main())
    assert seen == [1]
