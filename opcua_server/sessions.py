"""Session-level security of the mock 800xA server, on top of asyncua 2.1.0.

asyncua's ``UaProcessor`` (one per TCP connection and secure channel) keeps a
single ``session``: a second ``CreateSession`` on the same channel replaces
it, and every later request runs as whichever session was activated last,
whatever ``AuthenticationToken`` it carries (measured: a viewer's request ran
as the operator). It also serves ``CreateSession``/``ActivateSession`` on an
unencrypted channel, checks passwords inside the event loop, lets any session
delete any subscription, and reports the node's ``UserAccessLevel`` and
``UserExecutable`` whoever asks. ``PlantProcessor`` closes those holes:

* **One session per secure channel.** A ``CreateSession`` while the channel's
  session is open is refused (``BadTooManySessions``; open another
  connection), and every request must carry that session's
  ``AuthenticationToken`` (else ``BadSessionIdInvalid``), so the identity is
  the session's, never another one's.
* **No session on an unencrypted channel.** Unless the server was started
  with ``--insecure``, ``CreateSession`` and ``ActivateSession`` on a
  SecurityPolicy#None channel are refused (``BadSecurityModeRejected``):
  that channel serves discovery (GetEndpoints, FindServers) only, so it is
  no password oracle.
* **Passwords off the event loop, failed logins throttled.** scrypt runs in
  a one-thread executor (the plant clock and other sessions go on); after
  ``LoginThrottle.free_failures`` failed logins from one client (peer address
  and client certificate) each further attempt must wait a doubling delay
  (``base_delay_s`` .. ``max_delay_s``); an attempt inside the delay is
  refused at once (``BadUserAccessDenied``) without hashing.
* **Subscriptions belong to their session.** Delete/modify/publishing-mode/
  monitored-item/republish requests naming another session's subscription
  are refused (``BadSubscriptionIdInvalid``); a transfer only between
  sessions of the same user; ``ConditionRefresh``/``ConditionRefresh2`` on
  another session's subscription is refused with ``BadUserAccessDenied``
  (Part 9, 5.5.7: the server verifies the subscription is the calling
  session's; asyncua does not, so a viewer could inject refresh events
  into an operator's subscription).
* **Per-role access attributes.** ``UserAccessLevel`` has CurrentWrite only
  where the reading session's role may write the node, ``UserExecutable`` is
  true only for the role's methods.
* **IndexRange on reads** (asyncua ignores it and returns the whole array):
  a one-dimensional ``start:end`` or ``index`` range reads that part of an
  array value (Part 4, 7.22 NumericRange; an end past the array is cut, a
  start past it is ``BadIndexRangeNoData``, a malformed range
  ``BadIndexRangeInvalid``), so a client reads only the tail of a long list.

The plant server installs this processor (``install``) and attaches a
``SessionGuard`` to asyncua's internal server; without one the processor
behaves like asyncua's.
"""

from __future__ import annotations

import asyncio
import hashlib
import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

from asyncua import ua
from asyncua.common.utils import ServiceError
from asyncua.crypto.security_policies import SecurityPolicyNone
from asyncua.server import binary_server_asyncio
from asyncua.server.internal_session import SessionState
from asyncua.server.uaprocessor import UaProcessor
from asyncua.ua.ua_binary import struct_from_binary

log = logging.getLogger("opcua_server.sessions")


def _req(name: str) -> ua.NodeId:
    return ua.NodeId(getattr(ua.ObjectIds, f"{name}Request_Encoding_DefaultBinary"))


CREATE, ACTIVATE = _req("CreateSession"), _req("ActivateSession")
SESSIONLESS = frozenset({CREATE, _req("FindServers"), _req("GetEndpoints"), _req("RegisterServer"),
                         _req("RegisterServer2"), _req("CloseSecureChannel")})
READ, DELETE_SUBSCRIPTIONS, CALL = _req("Read"), _req("DeleteSubscriptions"), _req("Call")
CONDITION_REFRESH = frozenset({ua.NodeId(ua.ObjectIds.ConditionType_ConditionRefresh),
                               ua.NodeId(ua.ObjectIds.ConditionType_ConditionRefresh2)})
TRANSFER = _req("TransferSubscriptions")
ONE_SUBSCRIPTION = {  # request -> its parameters type, each naming one SubscriptionId
    _req("ModifySubscription"): ua.ModifySubscriptionParameters,
    _req("CreateMonitoredItems"): ua.CreateMonitoredItemsParameters,
    _req("ModifyMonitoredItems"): ua.ModifyMonitoredItemsParameters,
    _req("DeleteMonitoredItems"): ua.DeleteMonitoredItemsParameters,
    _req("SetMonitoringMode"): ua.SetMonitoringModeParameters,
    _req("Republish"): ua.RepublishParameters,
}
SET_PUBLISHING_MODE = _req("SetPublishingMode")
CURRENT_WRITE = ua.AccessLevel.CurrentWrite.mask


@dataclass
class LoginThrottle:
    """Failed-login back-off per client (peer host and certificate thumbprint).

    After ``free_failures`` consecutive failures the client must wait
    ``base_delay_s * 2**(k - 1)`` s (k: failures beyond the free ones), at
    most ``max_delay_s``, before its next attempt is checked; a success
    clears its record.
    """

    free_failures: int = 3
    base_delay_s: float = 0.5
    max_delay_s: float = 30.0
    failures: dict = field(default_factory=dict)   # client -> (count, time of last failure)
    refused_without_check: int = 0

    def wait_s(self, client, now: float) -> float:
        count, last = self.failures.get(client, (0, 0.0))
        if count < self.free_failures:
            return 0.0
        delay = min(self.base_delay_s * 2 ** (count - self.free_failures), self.max_delay_s)
        return max(last + delay - now, 0.0)

    def failed(self, client, now: float) -> None:
        count, _ = self.failures.get(client, (0, 0.0))
        self.failures[client] = (count + 1, now)

    def succeeded(self, client) -> None:
        self.failures.pop(client, None)


@dataclass
class SessionGuard:
    """What ``PlantProcessor`` needs from the plant server.

    ``writable_roles``: node id -> roles that may write its value;
    ``methods_by_role``: role -> method node ids it may call;
    ``allow_none_sessions``: ``--insecure`` (sessions on the None channel).
    """

    writable_roles: dict
    methods_by_role: dict
    allow_none_sessions: bool = False
    throttle: LoginThrottle = field(default_factory=LoginThrottle)
    executor: ThreadPoolExecutor = field(
        default_factory=lambda: ThreadPoolExecutor(1, thread_name_prefix="password-check"))


class PlantProcessor(UaProcessor):
    """asyncua's processor with the checks of the module docstring."""

    @property
    def guard(self) -> SessionGuard | None:
        return getattr(self.iserver, "plant_guard", None)

    async def _process_message(self, typeid, requesthdr, seqhdr, body):
        guard = self.guard
        if guard is None:
            return await super()._process_message(typeid, requesthdr, seqhdr, body)
        if typeid in (CREATE, ACTIVATE) and not guard.allow_none_sessions and \
                self._connection.security_policy.URI == SecurityPolicyNone.URI:
            log.warning("refused a session request on an unencrypted (None) secure channel "
                        "from %s", self.name)
            raise ServiceError(ua.StatusCodes.BadSecurityModeRejected)
        session = self.session
        live = session is not None and session.state != SessionState.Closed
        if typeid == CREATE and live:
            log.warning("refused a second session on one secure channel from %s", self.name)
            raise ServiceError(ua.StatusCodes.BadTooManySessions)
        if typeid not in SESSIONLESS and live and requesthdr.AuthenticationToken != session.auth_token:
            log.warning("refused a request whose authentication token is not the channel's "
                        "session's, from %s", self.name)
            raise ServiceError(ua.StatusCodes.BadSessionIdInvalid)
        if typeid == ACTIVATE:
            await self._check_password(guard, body)
        elif live and session.is_activated():
            if typeid == READ:
                return await self._read(guard, requesthdr, seqhdr, body)
            if typeid == DELETE_SUBSCRIPTIONS:
                return await self._delete_subscriptions(requesthdr, seqhdr, body)
            if typeid == CALL and await self._call_with_refresh(typeid, requesthdr, seqhdr, body):
                return True
            self._check_subscription_owner(typeid, body)
        return await super()._process_message(typeid, requesthdr, seqhdr, body)

    # ------------------------------------------------------------- identity
    def _client_key(self) -> tuple:
        certificate = self._connection.security_policy.peer_certificate or b""
        host = self.name[0] if isinstance(self.name, tuple) else self.name
        return host, hashlib.sha256(certificate).hexdigest()

    async def _check_password(self, guard: SessionGuard, body) -> None:
        """Check a user name and password in the executor, throttled per client.

        The verdict is handed to the user manager (``PlantUserManager.verdicts``),
        which asyncua's ``activate_session`` then asks without hashing again.
        """
        session = self.session
        if session is None:
            return  # re-activation of a session from another channel: asyncua checks it
        params = struct_from_binary(ua.ActivateSessionParameters, body.copy())
        token = params.UserIdentityToken
        if not isinstance(token, ua.UserNameIdentityToken):
            return  # asyncua refuses the other token types (only user names are offered)
        try:
            username, password = self.iserver.decrypt_user_token(session, token)
        except Exception:
            raise ServiceError(ua.StatusCodes.BadIdentityTokenInvalid) from None
        client, throttle = self._client_key(), guard.throttle
        wait = throttle.wait_s(client, time.monotonic())
        if wait > 0:
            throttle.refused_without_check += 1
            log.warning("refused a login of %r from %s: %d failed logins, next check in %.1f s",
                        username, client[0], throttle.failures[client][0], wait)
            raise ServiceError(ua.StatusCodes.BadUserAccessDenied)
        manager = self.iserver.user_manager
        user = await asyncio.get_running_loop().run_in_executor(
            guard.executor, manager.check, username, password)
        if user is None:
            throttle.failed(client, time.monotonic())
            log.warning("failed login of %r from %s", username, client[0])
            raise ServiceError(ua.StatusCodes.BadUserAccessDenied)
        throttle.succeeded(client)
        manager.verdicts[(username, password)] = user

    # -------------------------------------------------------- subscriptions
    def _owned(self, subscription_id) -> bool:
        sub = self.iserver.subscription_service.subscriptions.get(subscription_id)
        return sub is not None and sub.session_id == self.session.session_id

    def _check_subscription_owner(self, typeid, body) -> None:
        ids = []
        if typeid in ONE_SUBSCRIPTION:
            ids = [struct_from_binary(ONE_SUBSCRIPTION[typeid], body.copy()).SubscriptionId]
        elif typeid == SET_PUBLISHING_MODE:
            ids = struct_from_binary(ua.SetPublishingModeParameters, body.copy()).SubscriptionIds
        elif typeid == TRANSFER:
            services = self.iserver.subscription_service.subscriptions
            sessions = {s.session_id: s for s in self.iserver._external_sessions.values()} \
                if hasattr(self.iserver, "_external_sessions") else {}
            me = getattr(self.session.user, "name", None)
            for sid in struct_from_binary(ua.TransferSubscriptionsParameters,
                                          body.copy()).SubscriptionIds:
                sub = services.get(sid)
                owner = sessions.get(sub.session_id) if sub is not None else None
                if sub is not None and getattr(getattr(owner, "user", None), "name", None) != me:
                    log.warning("refused a transfer of another user's subscription %s", sid)
                    raise ServiceError(ua.StatusCodes.BadUserAccessDenied)
            return
        for sid in ids:
            if self.iserver.subscription_service.subscriptions.get(sid) is not None \
                    and not self._owned(sid):
                log.warning("refused a request on another session's subscription %s", sid)
                raise ServiceError(ua.StatusCodes.BadSubscriptionIdInvalid)

    def _foreign_refresh(self, method) -> bool:
        """A ConditionRefresh(2) naming an existing subscription of another session."""
        if method.MethodId not in CONDITION_REFRESH or not method.InputArguments:
            return False
        sid = getattr(method.InputArguments[0], "Value", None)
        return isinstance(sid, int) and not isinstance(sid, bool) and \
            self.iserver.subscription_service.subscriptions.get(sid) is not None and \
            not self._owned(sid)

    async def _call_with_refresh(self, typeid, requesthdr, seqhdr, body) -> bool:
        """Answer a Call that refreshes another session's subscription (False: not one;
        asyncua answers it)."""
        params = struct_from_binary(ua.CallParameters, body.copy())
        foreign = [self._foreign_refresh(m) for m in params.MethodsToCall]
        if not any(foreign):
            return False
        permissions = self._connection.security_policy.permissions
        if permissions is not None and not permissions.check_validity(self.session.user, typeid,
                                                                       body.copy()):
            raise ServiceError(ua.StatusCodes.BadUserAccessDenied)
        self.session.touch()
        results = []
        for method, refused in zip(params.MethodsToCall, foreign):
            if refused:
                log.warning("refused ConditionRefresh of subscription %s: not this session's",
                            method.InputArguments[0].Value)
                results.append(ua.CallMethodResult(
                    StatusCode=ua.StatusCode(ua.StatusCodes.BadUserAccessDenied)))
            else:
                results.extend(await self.session.call([method]))
        response = ua.CallResponse()
        response.Results = results
        self.send_response(requesthdr.RequestHandle, seqhdr, response)
        return True

    async def _delete_subscriptions(self, requesthdr, seqhdr, body):
        params = struct_from_binary(ua.DeleteSubscriptionsParameters, body)
        own = [sid for sid in params.SubscriptionIds if self._owned(sid)]
        deleted = iter(await self.session.delete_subscriptions(own) if own else [])
        results = []
        for sid in params.SubscriptionIds:
            if sid in own:
                results.append(next(deleted))
            else:
                log.warning("refused deleting subscription %s: not this session's", sid)
                results.append(ua.StatusCode(ua.StatusCodes.BadSubscriptionIdInvalid))
        response = ua.DeleteSubscriptionsResponse()
        response.Results = results
        self.send_response(requesthdr.RequestHandle, seqhdr, response)
        return True

    # --------------------------------------------------------------- access
    async def _read(self, guard: SessionGuard, requesthdr, seqhdr, body):
        params = struct_from_binary(ua.ReadParameters, body)
        results = await self.session.read(params)
        role = getattr(self.session.user, "plant_role", None)
        for k, item in enumerate(params.NodesToRead):
            value = results[k]
            if not value.StatusCode.is_good():
                continue
            if item.IndexRange:
                results[k] = _index_range(value, item.IndexRange)
            elif item.AttributeId == ua.AttributeIds.UserAccessLevel:
                level = int(value.Value.Value)
                if role not in guard.writable_roles.get(item.NodeId, ()):
                    level &= ~CURRENT_WRITE
                results[k] = ua.DataValue(ua.Variant(level, ua.VariantType.Byte))
            elif item.AttributeId == ua.AttributeIds.UserExecutable:
                allowed = item.NodeId in guard.methods_by_role.get(role, set())
                results[k] = ua.DataValue(ua.Variant(bool(value.Value.Value) and allowed,
                                                     ua.VariantType.Boolean))
        response = ua.ReadResponse()
        response.Results = results
        self.send_response(requesthdr.RequestHandle, seqhdr, response)
        return True


def _index_range(value: ua.DataValue, text: str) -> ua.DataValue:
    """The part ``text`` ("start:end" or "index", inclusive) of an array value."""
    start, _, end = text.partition(":")
    try:
        first, last = int(start), int(end) if end else int(start)
        if first < 0 or last < first or (end and last == first):
            raise ValueError(text)
    except ValueError:
        return ua.DataValue(StatusCode=ua.StatusCode(ua.StatusCodes.BadIndexRangeInvalid))
    variant = value.Value
    items = variant.Value if variant is not None else None
    if not isinstance(items, (list, tuple)):
        return ua.DataValue(StatusCode=ua.StatusCode(ua.StatusCodes.BadIndexRangeInvalid))
    if first >= len(items):
        return ua.DataValue(StatusCode=ua.StatusCode(ua.StatusCodes.BadIndexRangeNoData))
    return ua.DataValue(ua.Variant(list(items[first:last + 1]), variant.VariantType),
                        SourceTimestamp=value.SourceTimestamp,
                        ServerTimestamp=value.ServerTimestamp)


def install() -> None:
    """Make asyncua's binary server create ``PlantProcessor`` for each connection."""
    binary_server_asyncio.UaProcessor = PlantProcessor
