"""The DDS side of ROS 2: topic-name mangling, the QoS profiles of ``rclpy``, and a Cyclone DDS
domain bound to one network interface (loopback by default).

* Topic names: ROS 2's DDS RMWs publish the ROS topic ``/a/b`` as the DDS topic ``rt/a/b``
  (``rmw_cyclonedds_cpp/src/namespace_prefix.hpp``: ``rt`` topics, ``rq``/``rr`` service
  request/reply); :func:`dds_topic_name`.
* QoS (``rmw/qos_profiles.h``, as ``rmw_cyclonedds`` maps them onto DDS): ``SENSOR_DATA``
  (``qos_profile_sensor_data``: best effort, volatile, keep last 5) for images and camera info,
  ``DEFAULT`` (reliable, volatile, keep last 10) for commands, status and results, and ``TF``
  (tf2_ros' ``DynamicBroadcasterQoS``: reliable, volatile, keep last 100) for ``/tf``.
* :class:`DdsDomain`: a Cyclone DDS domain configured in XML (no ``CYCLONEDDS_URI`` needed) on
  one interface; on loopback, multicast is off and discovery is unicast to 127.0.0.1, so nothing
  leaves the machine. Any other interface must be asked for (``allow_remote``), as ``brave6d
  serve`` asks for ``--allow-remote``.
"""

from __future__ import annotations

import ipaddress
import logging
import threading
from dataclasses import dataclass
from typing import Any, Callable

from brave6d.core.errors import BraveError

log = logging.getLogger(__name__)

#: Prefix of ROS 2 topics on DDS (rmw's ``ROS_TOPIC_PREFIX``).
ROS_TOPIC_PREFIX = "rt"
#: Largest DDS domain id ROS 2 accepts (``ROS_DOMAIN_ID``; Cyclone's UDP port formula runs out above 232).
MAX_DOMAIN_ID = 232
#: Participant indices probed in unicast discovery (Cyclone's ``MaxAutoParticipantIndex``):
#: how many DDS processes can meet on one machine with multicast off.
MAX_PARTICIPANTS = 32
#: UDP receive buffer asked for (the kernel caps it at net.core.rmem_max): a 640x480 frame is
#: ~2 MB of fragments arriving at once; Cyclone's default 1 MiB loses best-effort images when the
#: receiving process is busy (the ROS 2 DDS tuning guide's advice for large messages).
SOCKET_RECEIVE_BUFFER = "16MiB"


def dds_topic_name(ros_topic: str) -> str:
    """``'/brave6d/rgb/image_raw'`` -> ``'rt/brave6d/rgb/image_raw'`` (a fully qualified ROS name)."""
    if not ros_topic.startswith("/") or ros_topic.endswith("/") or "//" in ros_topic:
        raise BraveError(f"ROS topic {ros_topic!r}: must be fully qualified ('/a/b'), without a trailing '/'")
    return f"{ROS_TOPIC_PREFIX}{ros_topic}"


@dataclass(frozen=True)
class QosProfile:
    """A ROS 2 QoS profile (the part ``rmw_cyclonedds`` maps onto DDS for these topics)."""

    name: str
    reliable: bool
    depth: int
    transient_local: bool = False

    def to_dds(self) -> Any:
        """The Cyclone DDS ``Qos`` of this profile (as ``rmw_cyclonedds``' ``create_readwrite_qos``
        sets it; the data representation pinned to XCDR1, the one ROS 2 types allow)."""
        from cyclonedds.qos import Policy, Qos
        from cyclonedds.util import duration

        reliability = (Policy.Reliability.Reliable(max_blocking_time=duration(seconds=1)) if self.reliable
                       else Policy.Reliability.BestEffort)
        durability = Policy.Durability.TransientLocal if self.transient_local else Policy.Durability.Volatile
        return Qos(reliability, durability, Policy.History.KeepLast(self.depth),
                   Policy.DataRepresentation(use_cdrv0_representation=True))


SENSOR_DATA = QosProfile("sensor_data", reliable=False, depth=5)
DEFAULT = QosProfile("default", reliable=True, depth=10)
TF = QosProfile("tf", reliable=True, depth=100)


def is_loopback(interface: str) -> bool:
    """True for a loopback address (127.0.0.0/8, ::1) or interface name (``lo``)."""
    if interface in ("lo", "localhost"):
        return True
    try:
        return ipaddress.ip_address(interface).is_loopback
    except ValueError:
        return False


def cyclone_config(interface: str = "127.0.0.1", peers: tuple[str, ...] = ()) -> str:
    """Cyclone DDS XML for one ``interface`` (an address or an interface name). On loopback:
    multicast off, unicast discovery to 127.0.0.1. Elsewhere: multicast as the network allows,
    plus unicast discovery to ``peers`` when given."""
    loopback = is_loopback(interface)
    try:
        ipaddress.ip_address(interface)
        nic = f'<NetworkInterface address="{interface}"/>'
    except ValueError:
        if not interface.replace("-", "").replace("_", "").replace(".", "").isalnum():
            raise BraveError(f"--interface {interface!r}: not an address or an interface name") from None
        nic = f'<NetworkInterface name="{interface}"/>'
    peer_list = list(peers) + (["127.0.0.1"] if loopback and not peers else [])
    for p in peer_list:
        if not all(c.isalnum() or c in ".-:_" for c in p):
            raise BraveError(f"--peer {p!r}: not a host name or address")
    peer_xml = "".join(f'<Peer address="{p}"/>' for p in peer_list)
    multicast = "false" if loopback else "default"
    discovery = (f"<ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>{MAX_PARTICIPANTS}"
                 f"</MaxAutoParticipantIndex>" + (f"<Peers>{peer_xml}</Peers>" if peer_xml else ""))
    return ('<CycloneDDS><Domain Id="any"><General><Interfaces>' + nic + "</Interfaces>"
            f"<AllowMulticast>{multicast}</AllowMulticast></General>"
            f"<Discovery>{discovery}</Discovery>"
            f'<Internal><SocketReceiveBufferSize min="default" max="{SOCKET_RECEIVE_BUFFER}"/></Internal>'
            "</Domain></CycloneDDS>")


def check_domain_id(domain_id: int) -> int:
    if not 0 <= int(domain_id) <= MAX_DOMAIN_ID:
        raise BraveError(f"--domain-id {domain_id}: must be in 0..{MAX_DOMAIN_ID} (as ROS_DOMAIN_ID)")
    return int(domain_id)


def check_interface(interface: str, allow_remote: bool) -> str:
    """``interface`` when it is loopback or ``allow_remote``; else :class:`BraveError` (one line)."""
    if not is_loopback(interface) and not allow_remote:
        raise BraveError(f"--interface {interface}: not loopback; DDS on a network interface is reachable by every "
                         "host on it: add --allow-remote to do that on purpose")
    return interface


#: Cyclone domains configured by this process: a domain id is configured once per process (Cyclone
#: refuses a second configuration), and the ``Domain`` object must outlive its participants.
_DOMAINS: dict[int, tuple[str, Any]] = {}
_DOMAINS_LOCK = threading.Lock()


def _configured_domain(domain_id: int, config: str) -> Any:
    from cyclonedds.domain import Domain

    with _DOMAINS_LOCK:
        if domain_id in _DOMAINS:
            known, domain = _DOMAINS[domain_id]
            if known != config:
                raise BraveError(f"DDS domain {domain_id} is already configured in this process with another "
                                 "interface or peers")
            return domain
        domain = Domain(domain_id, config)
        _DOMAINS[domain_id] = (config, domain)
        return domain


class DdsDomain:
    """One DDS domain participant on a configured interface, with typed readers and writers of
    ROS 2 topics. Writers and readers are created on first use and kept (one per topic)."""

    def __init__(self, domain_id: int = 0, interface: str = "127.0.0.1", *, allow_remote: bool = False,
                 peers: tuple[str, ...] = ()) -> None:
        from cyclonedds.domain import DomainParticipant

        self.domain_id = check_domain_id(domain_id)
        self.interface = check_interface(interface, allow_remote)
        self._domain = _configured_domain(self.domain_id, cyclone_config(interface, peers))
        self.participant = DomainParticipant(self.domain_id)
        self._topics: dict[str, Any] = {}
        self._writers: dict[str, Any] = {}
        self._readers: dict[str, Any] = {}
        self._dispatch: _Dispatcher | None = None

    def _topic(self, ros_topic: str, msg_type: type) -> Any:
        from cyclonedds.topic import Topic

        name = dds_topic_name(ros_topic)
        topic = self._topics.get(name)
        if topic is None:
            topic = self._topics[name] = Topic(self.participant, name, msg_type)
        elif topic.data_type is not msg_type:
            raise BraveError(f"topic {ros_topic}: already used with type {topic.data_type.__name__}, "
                             f"not {msg_type.__name__}")
        return topic

    def writer(self, ros_topic: str, msg_type: type, qos: QosProfile) -> Any:
        """The DataWriter of ``ros_topic`` (created with ``qos`` on first use)."""
        from cyclonedds.pub import DataWriter

        w = self._writers.get(ros_topic)
        if w is None:
            w = self._writers[ros_topic] = DataWriter(self.participant, self._topic(ros_topic, msg_type), qos.to_dds())
        return w

    def reader(self, ros_topic: str, msg_type: type, qos: QosProfile,
               on_data: Callable[[Any], None] | None = None) -> Any:
        """The DataReader of ``ros_topic``; with ``on_data``, every sample is handed to it on this
        domain's dispatch thread (one for all readers; keep ``on_data`` short)."""
        from cyclonedds.sub import DataReader

        r = self._readers.get(ros_topic)
        if r is None:
            r = self._readers[ros_topic] = DataReader(self.participant, self._topic(ros_topic, msg_type), qos.to_dds())
            if on_data is not None:
                self._dispatcher().add(r, on_data)
        return r

    def _dispatcher(self) -> "_Dispatcher":
        if self._dispatch is None:
            self._dispatch = _Dispatcher(self.participant, f"dds-dispatch-{self.domain_id}")
        return self._dispatch

    def publish(self, ros_topic: str, sample: Any, qos: QosProfile) -> None:
        self.writer(ros_topic, type(sample), qos).write(sample)

    def close(self) -> None:
        """Stop the dispatch thread; delete the participant (and with it every reader and writer)."""
        if self._dispatch is not None:
            self._dispatch.stop()
            self._dispatch = None
        self._readers.clear()
        self._writers.clear()
        self._topics.clear()
        participant, self.participant = self.participant, None
        if participant is not None:
            # Deleting a participant deletes its readers and writers in Cyclone; the Python
            # wrappers only do it when garbage collected (listener threads may hold references).
            participant.__del__()

    def __enter__(self) -> "DdsDomain":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _Dispatcher:
    """One thread that waits on a WaitSet of read conditions and hands every new sample to its
    reader's callback.

    Why not Cyclone listeners: a listener runs on Cyclone's receive thread, which then waits for
    Python's GIL in every callback; while it waits, a fragmented sample (a 640x480 depth image is
    ~850 UDP fragments) overflows the socket buffer and a best-effort image is lost. Here the
    receive thread only stores samples (each reader keeps its QoS history) and signals the WaitSet.
    """

    POLL_NS = 100_000_000  # the thread re-checks for stop() this often

    def __init__(self, participant: Any, name: str) -> None:
        from cyclonedds.core import WaitSet

        self._waitset = WaitSet(participant)
        self._entries: list[tuple[Any, Any, Callable[[Any], None]]] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def add(self, reader: Any, on_data: Callable[[Any], None]) -> None:
        from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState

        condition = ReadCondition(reader, SampleState.NotRead | ViewState.Any | InstanceState.Any)
        with self._lock:
            self._entries.append((reader, condition, on_data))
            self._waitset.attach(condition)

    def _run(self) -> None:
        while not self._stop.is_set():
            self._waitset.wait(self.POLL_NS)
            with self._lock:
                entries = list(self._entries)
            for reader, condition, on_data in entries:
                if self._stop.is_set():
                    return
                for sample in reader.take(N=64, condition=condition):
                    try:
                        on_data(sample)
                    except Exception:  # one bad callback must not stop every reader
                        log.exception("DDS callback of %s failed", reader.topic.name)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
