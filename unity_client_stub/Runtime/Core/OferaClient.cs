// WebSocket client of the OFERA server: System.Net.WebSockets.ClientWebSocket, a receive loop off the
// main thread into pooled buffers, newest-frame handoff to the main thread, bs sending at the
// headset's rate, reconnect with exponential backoff and a fresh handshake, latency statistics.
// UnityEngine-free (runs under mono in Tests/run.sh), C# 7.2.
using System;
using System.Collections.Concurrent;
using System.Collections.Generic;
using System.Net.WebSockets;
using System.Threading;
using System.Threading.Tasks;

namespace Ofera.Client
{
    public sealed class OferaClientOptions
    {
        /// <summary>ws:// or wss:// URL; a URL without a path gets /v1/stream.</summary>
        public string Url = "ws://127.0.0.1:8000/v1/stream";
        public string Layout = "ovr63";
        public string Avatar = "default";
        /// <summary>f32, f16, q13, or params (PROTOCOL.md 13: frames carry 68 values and the client deforms the avatar
        /// from its rig, AvatarData.Rig; with DecodeValues on the receive thread, RigDeformer, else on the GPU).</summary>
        public string Encoding = "f32";
        /// <summary>unity (default: the server mirrors x for Unity) or flame.</summary>
        public string Coords = "unity";
        public bool Sparse = true;
        /// <summary>Ask for temporal deltas (f16, q13; PROTOCOL.md 7.1): key frames, then only what moved. A delta
        /// frame the client cannot apply makes it send `resync` itself.</summary>
        public bool Delta;
        /// <summary>Headset profile selecting the server's BDA, e.g. quest_pro; null to omit.</summary>
        public string Device = "quest_pro";
        public string Token;
        public long? MaxGaussians;
        /// <summary>With Coords = flame: mirror what arrives to Unity's handedness on the receive thread.</summary>
        public bool MirrorFlameToUnity;

        public bool Reconnect = true;
        public double InitialBackoffSeconds = 0.5;
        public double MaxBackoffSeconds = 30;
        public double ConnectTimeoutSeconds = 10;
        /// <summary>Time allowed from hello to the complete avatar.</summary>
        public double HandshakeTimeoutSeconds = 60;
        /// <summary>ping interval for network round-trip statistics (0: no pings).</summary>
        public double PingIntervalSeconds = 2;
        public int MaxMessageSize = Protocol.MaxServerMessage;
        public int InitialReceiveBuffer = 256 * 1024;

        /// <summary>Keep each frame's wire arrays (FrameData.Payload) for the GPU upload path.</summary>
        public bool KeepPayload;
        /// <summary>With KeepPayload: also decode frames into floats (false: the GPU decodes; only checks run on the CPU).</summary>
        public bool DecodeValues = true;

        /// <summary>Rooms (PROTOCOL.md 12; a server without rooms ignores these): room to join, publish this client's face
        /// (default true; false: watch only), receive one's own stream (default false), and the room token a server with
        /// a room secret requires (hex HMAC-SHA256 of the room name, from your app server).</summary>
        public string Room;
        public bool? Publish;
        public bool? Self;
        public string RoomToken;
    }

    public enum ClientStatus { Stopped, Connecting, AwaitingWelcome, ReceivingAvatar, Streaming, Reconnecting, Failed }

    public enum ClientEventKind { Status, ServerError, ProtocolError, Info }

    public sealed class ClientEvent
    {
        public ClientEventKind Kind;
        public ClientStatus Status;
        public string Message;
        /// <summary>For ServerError: the server's error message.</summary>
        public ErrorMessage Error;
        public override string ToString() { return Kind + ": " + Message; }
    }

    public sealed class ClientStats
    {
        public long FramesReceived;
        /// <summary>Frames replaced by a newer one before the main thread took them.</summary>
        public long FramesDropped;
        /// <summary>Frames refused by the decoder (non-fatal error while streaming).</summary>
        public long FramesInvalid;
        /// <summary>bs seq values the server skipped (gaps in frame seq).</summary>
        public long FramesSkippedByServer;
        public long BsSent;
        /// <summary>Samples replaced before they could be sent.</summary>
        public long BsSuperseded;
        public long BytesReceived;
        public long Sessions;
        public long Reconnects;
        public long ServerErrors;
        /// <summary>bs taken -> frame received (from the echoed t), µs.</summary>
        public readonly LatencyStats RoundTrip = new LatencyStats();
        /// <summary>bs taken -> frame taken by the main thread, µs.</summary>
        public readonly LatencyStats RoundTripAtTake = new LatencyStats();
        /// <summary>The server's own `total` stage, µs.</summary>
        public readonly LatencyStats ServerTotal = new LatencyStats();
        /// <summary>ping -> pong, µs (network and event loop only).</summary>
        public readonly LatencyStats PingRoundTrip = new LatencyStats();
    }

    /// <summary>
    /// Thread model: Start() runs a supervisor task on the thread pool (connect, handshake, receive loop,
    /// reconnect). A send task runs per session. The main thread calls SubmitBlendshapes, TryTakeAvatar,
    /// TryTakeFrame and TryDequeueEvent; none of them blocks on the network.
    /// Frames go through a <see cref="FrameExchange"/>: the receive thread decodes into a pooled FrameData
    /// and publishes it as its member's "ready" frame (a ready frame the main thread has not taken is
    /// recycled and counted as dropped); the main thread holds at most one per member until its next
    /// TryTakeFrame. In a room, members' avatars and departures arrive through TryTakeRoomEvent.
    /// </summary>
    public sealed class OferaClient : IDisposable
    {
        readonly OferaClientOptions _opt;
        readonly Uri _uri;
        readonly int _layoutLength;
        public readonly ClientStats Stats = new ClientStats();

        CancellationTokenSource _cts;
        Task _supervisor;
        volatile ClientStatus _status = ClientStatus.Stopped;
        volatile bool _byeRequested;
        volatile string _member;
        int _sessionNumber;

        // blendshape mailbox (newest wins)
        readonly object _bsLock = new object();
        readonly float[] _bsLatest;
        long _bsT;
        bool _bsPending;
        readonly SemaphoreSlim _sendSignal = new SemaphoreSlim(0, 1);

        // frames (own avatar and room members)
        readonly FrameExchange _frames = new FrameExchange();
        readonly ConcurrentQueue<RoomEvent> _roomEvents = new ConcurrentQueue<RoomEvent>();

        // avatar handoff
        readonly object _avatarLock = new object();
        AvatarData _pendingAvatar;
        Welcome _pendingWelcome;
        int _pendingSession;

        readonly ConcurrentQueue<ClientEvent> _events = new ConcurrentQueue<ClientEvent>();
        readonly ConcurrentQueue<byte[]> _raw = new ConcurrentQueue<byte[]>();
        volatile ClientWebSocket _currentWs;
        byte[] _rx;
        readonly Random _random = new Random();

        public OferaClient(OferaClientOptions options)
        {
            if (options == null) throw new ArgumentNullException("options");
            _opt = options;
            _layoutLength = Protocol.LayoutLength(options.Layout);
            if (_layoutLength < 0) throw new ArgumentException("unknown layout '" + options.Layout + "'; expected one of " + string.Join(", ", Protocol.Layouts));
            if (!Protocol.Contains(ParamsProtocol.HelloEncodings, options.Encoding)) throw new ArgumentException("unknown encoding '" + options.Encoding + "'; expected f32, f16, q13 or params");
            if (!Protocol.Contains(Protocol.CoordsNames, options.Coords)) throw new ArgumentException("unknown coords '" + options.Coords + "'; expected unity or flame");
            _uri = MakeUri(options.Url);
            _bsLatest = new float[_layoutLength];
            _rx = new byte[Math.Max(4096, options.InitialReceiveBuffer)];
        }

        public static Uri MakeUri(string url)
        {
            Uri u;
            if (!Uri.TryCreate(url, UriKind.Absolute, out u) || (u.Scheme != "ws" && u.Scheme != "wss"))
                throw new ArgumentException("server URL '" + url + "' must be absolute ws:// or wss://, e.g. ws://192.168.1.20:8000/v1/stream");
            if (u.AbsolutePath == "/" || u.AbsolutePath.Length == 0)
                u = new Uri(u, Protocol.Endpoint);
            return u;
        }

        public ClientStatus Status { get { return _status; } }
        public OferaClientOptions Options { get { return _opt; } }
        /// <summary>Number of the current (or last) session, 1 for the first.</summary>
        public int SessionNumber { get { return Volatile.Read(ref _sessionNumber); } }
        /// <summary>Rooms: this client's member id in the current (or last) room session (welcome.member); null outside a room.</summary>
        public string Member { get { return _member; } }

        // ------------------------------------------------------------------ lifecycle

        public void Start()
        {
            if (_supervisor != null && !_supervisor.IsCompleted) return;
            _byeRequested = false;
            _cts = new CancellationTokenSource();
            CancellationToken token = _cts.Token;
            _supervisor = Task.Run(() => SuperviseAsync(token));
        }

        /// <summary>Sends bye if streaming, waits up to <paramref name="timeoutMs"/> for the close, then cancels.</summary>
        public void Stop(int timeoutMs = 1000)
        {
            if (_supervisor == null) return;
            _byeRequested = true;
            Signal();
            try { _supervisor.Wait(timeoutMs); } catch (AggregateException) { }
            _cts.Cancel();
            try { _supervisor.Wait(timeoutMs); } catch (AggregateException) { }
            _supervisor = null;
            SetStatus(ClientStatus.Stopped, null);
        }

        public void Dispose() { Stop(); }

        // ------------------------------------------------------------------ main-thread API

        /// <summary>
        /// Hands the newest face sample to the sender (copied; an unsent older sample is replaced).
        /// <paramref name="tMicros"/>: when it was taken, on <see cref="OferaClock"/>.
        /// </summary>
        public void SubmitBlendshapes(float[] weights, long tMicros)
        {
            if (weights == null || weights.Length < _layoutLength)
                throw new ArgumentException("layout " + _opt.Layout + " needs " + _layoutLength + " weights");
            lock (_bsLock)
            {
                Array.Copy(weights, _bsLatest, _layoutLength);
                _bsT = tMicros;
                if (_bsPending) Interlocked.Increment(ref Stats.BsSuperseded);
                _bsPending = true;
            }
            Signal();
        }

        void Signal()
        {
            try { if (_sendSignal.CurrentCount == 0) _sendSignal.Release(); }
            catch (SemaphoreFullException) { }
        }

        /// <summary>The avatar of a new session, once per session (null until then).</summary>
        public bool TryTakeAvatar(out AvatarData avatar, out Welcome welcome, out int session)
        {
            lock (_avatarLock)
            {
                avatar = _pendingAvatar; welcome = _pendingWelcome; session = _pendingSession;
                _pendingAvatar = null; _pendingWelcome = null;
            }
            if (avatar == null) return false;
            _frames.ReleaseBefore(session);  // the main thread has moved on: older sessions' member frames are free
            return true;
        }

        /// <summary>
        /// The newest frame not taken yet, or null. The returned object stays valid until the next call
        /// (it is then recycled); copy what you need. Check frame.SessionNumber against your avatar's.
        /// </summary>
        public FrameData TryTakeFrame() { return TryTakeFrame(null); }

        /// <summary>As <see cref="TryTakeFrame()"/> for one room member (null: the session's own avatar).</summary>
        public FrameData TryTakeFrame(string member)
        {
            FrameData f = _frames.Take(member);
            if (f != null && member == null && f.T != 0) Stats.RoundTripAtTake.Add(OferaClock.NowMicros() - f.T);
            return f;
        }

        /// <summary>Rooms: the next member joined (avatar complete) or left, in arrival order.</summary>
        /// <remarks>A member's last frame (from TryTakeFrame(member)) stays valid until you take its Left event (or,
        /// after a reconnect, an event or avatar of the new session): it then returns to the frame pool.</remarks>
        public bool TryTakeRoomEvent(out RoomEvent e)
        {
            if (!_roomEvents.TryDequeue(out e)) return false;
            if (e.Kind == RoomEventKind.Left) _frames.Release(e.Member);
            _frames.ReleaseBefore(e.Session);
            return true;
        }

        public bool TryDequeueEvent(out ClientEvent e) { return _events.TryDequeue(out e); }

        /// <summary>Diagnostics and tests: sends these exact bytes as one binary message on the current session.</summary>
        public void SendRawForTesting(byte[] message)
        {
            _raw.Enqueue(message);
            Signal();
        }

        /// <summary>Diagnostics and tests: drops the connection as a network failure would (the client reconnects).</summary>
        public void AbortConnectionForTesting()
        {
            ClientWebSocket ws = _currentWs;
            if (ws != null) { try { ws.Abort(); } catch (Exception) { } }
        }

        // ------------------------------------------------------------------ internals

        void Emit(ClientEventKind kind, string message, ErrorMessage error = null)
        {
            ClientEvent e = new ClientEvent { Kind = kind, Status = _status, Message = message, Error = error };
            _events.Enqueue(e);
            ClientEvent dropped;
            while (_events.Count > 256 && _events.TryDequeue(out dropped)) { }
        }

        void SetStatus(ClientStatus s, string message)
        {
            if (_status == s && message == null) return;
            _status = s;
            Emit(ClientEventKind.Status, message ?? s.ToString());
        }

        Hello BuildHello()
        {
            Hello h = new Hello();
            h.Layout = _opt.Layout;
            h.Avatar = _opt.Avatar;
            h.Encoding = _opt.Encoding;
            h.Coords = _opt.Coords;
            h.Sparse = _opt.Sparse;
            if (_opt.Delta) h.Delta = true;
            h.Device = string.IsNullOrEmpty(_opt.Device) ? null : _opt.Device;
            h.Token = string.IsNullOrEmpty(_opt.Token) ? null : _opt.Token;
            h.MaxGaussians = _opt.MaxGaussians;
            h.Room = string.IsNullOrEmpty(_opt.Room) ? null : _opt.Room;
            h.Publish = h.Room != null ? _opt.Publish : null;
            h.Self = h.Room != null ? _opt.Self : null;
            h.RoomToken = h.Room != null && !string.IsNullOrEmpty(_opt.RoomToken) ? _opt.RoomToken : null;
            return h;
        }

        sealed class SessionEnd
        {
            public bool GotWelcome;
            public bool Permanent;  // configuration error: do not retry
            public string Reason = "";
        }

        async Task SuperviseAsync(CancellationToken stop)
        {
            double backoff = _opt.InitialBackoffSeconds;
            while (!stop.IsCancellationRequested)
            {
                SessionEnd end = new SessionEnd();
                try
                {
                    await RunSessionAsync(stop, end).ConfigureAwait(false);
                }
                catch (OperationCanceledException) { end.Reason = stop.IsCancellationRequested ? "stopped" : "connection lost or timed out"; }
                catch (Exception e) { end.Reason = e.GetType().Name + ": " + e.Message; }
                if (stop.IsCancellationRequested || _byeRequested) break;
                if (end.Permanent) { SetStatus(ClientStatus.Failed, "giving up: " + end.Reason); return; }
                if (!_opt.Reconnect) { SetStatus(ClientStatus.Stopped, "session ended: " + end.Reason); return; }
                if (end.GotWelcome) backoff = _opt.InitialBackoffSeconds;
                double delay;
                lock (_random) delay = backoff * (0.8 + 0.4 * _random.NextDouble());
                SetStatus(ClientStatus.Reconnecting, "session ended (" + end.Reason + "); reconnecting in " + delay.ToString("F1") + " s");
                try { await Task.Delay(TimeSpan.FromSeconds(delay), stop).ConfigureAwait(false); }
                catch (OperationCanceledException) { break; }
                backoff = Math.Min(backoff * 2, _opt.MaxBackoffSeconds);
                Interlocked.Increment(ref Stats.Reconnects);
            }
        }

        async Task RunSessionAsync(CancellationToken stop, SessionEnd end)
        {
            ClientWebSocket ws = new ClientWebSocket();
            _currentWs = ws;
            CancellationTokenSource sessionCts = CancellationTokenSource.CreateLinkedTokenSource(stop);
            Task sender = null;
            try
            {
                SetStatus(ClientStatus.Connecting, "connecting to " + _uri);
                using (CancellationTokenSource cto = CancellationTokenSource.CreateLinkedTokenSource(stop))
                {
                    cto.CancelAfter(TimeSpan.FromSeconds(_opt.ConnectTimeoutSeconds));
                    await ws.ConnectAsync(_uri, cto.Token).ConfigureAwait(false);
                }
                int session = Interlocked.Increment(ref _sessionNumber);
                Interlocked.Increment(ref Stats.Sessions);
                _frames.Reset(session);
                lock (_bsLock) { _bsPending = false; }

                ClientConnection conn = new ClientConnection();
                conn.MaxMessageSize = _opt.MaxMessageSize;
                conn.MirrorFlameToUnity = _opt.MirrorFlameToUnity;
                conn.KeepPayload = _opt.KeepPayload;
                conn.DecodeValues = _opt.DecodeValues || !_opt.KeepPayload;
                MsgPackWriter hw = new MsgPackWriter(256);
                conn.EncodeHello(BuildHello(), hw);
                await ws.SendAsync(hw.Segment, WebSocketMessageType.Binary, true, stop).ConfigureAwait(false);
                SetStatus(ClientStatus.AwaitingWelcome, null);

                // the handshake (welcome and every avatar chunk) must finish in time
                CancellationTokenSource handshakeCts = CancellationTokenSource.CreateLinkedTokenSource(sessionCts.Token);
                handshakeCts.CancelAfter(TimeSpan.FromSeconds(_opt.HandshakeTimeoutSeconds));
                CancellationToken rxToken = handshakeCts.Token;
                bool handshakeDone = false;

                ServerMessage msg = new ServerMessage();
                long lastSeq = -1;
                while (true)
                {
                    int len = await ReceiveMessageAsync(ws, conn, rxToken).ConfigureAwait(false);
                    if (len == -1)
                    {
                        end.Reason = "server closed" + (ws.CloseStatus.HasValue ? " (" + (int)ws.CloseStatus.Value + " " + ws.CloseStatusDescription + ")" : "");
                        return;
                    }
                    Interlocked.Add(ref Stats.BytesReceived, len);
                    msg.Frame = _frames.DecodeTarget;
                    ServerMessageKind kind;
                    try
                    {
                        kind = conn.Receive(_rx, 0, len, msg);
                    }
                    catch (ProtocolException e)
                    {
                        if (!e.Fatal)
                        {
                            Interlocked.Increment(ref Stats.FramesInvalid);
                            Emit(ClientEventKind.ProtocolError, "dropped a bad message: " + e.Message);
                            DeltaState held = conn.Format != null ? conn.Format.Delta : null;
                            if (held != null && held.ResyncNeeded) // a lost delta frame: ask for a key frame
                            {
                                held.ResyncNeeded = false;
                                MsgPackWriter rw = new MsgPackWriter(16);
                                ClientMessageEncoder.Resync(rw);
                                _raw.Enqueue(rw.ToArray());
                                Signal();
                            }
                            continue;
                        }
                        Emit(ClientEventKind.ProtocolError, "fatal: " + e.Message);
                        end.Reason = e.Code;
                        await CloseQuietly(ws, (WebSocketCloseStatus)e.CloseCode, e.Code).ConfigureAwait(false);
                        return;
                    }
                    switch (kind)
                    {
                        case ServerMessageKind.Welcome:
                            end.GotWelcome = true;
                            _member = msg.Welcome.Member;
                            if (conn.InRoom) // a room session streams from welcome on; every avatar comes with a join
                            {
                                handshakeDone = true;
                                rxToken = sessionCts.Token;
                                handshakeCts.Dispose();
                                SetStatus(ClientStatus.Streaming, "room " + msg.Welcome.Room + ": member " + msg.Welcome.Member + (msg.Welcome.AvatarId != null ? ", publishing " + msg.Welcome.AvatarId : ", watching") + ", " + msg.Welcome.Encoding + (msg.Welcome.Sparse ? " sparse" : " dense") + ", coords " + msg.Welcome.Coords);
                            }
                            else SetStatus(ClientStatus.ReceivingAvatar, "welcome: session " + msg.Welcome.Session + ", " + msg.Welcome.Count + " Gaussians, " + msg.Welcome.Encoding + (msg.Welcome.Sparse ? " sparse" : " dense") + ", coords " + msg.Welcome.Coords);
                            sender = Task.Run(() => SendLoopAsync(ws, conn, sessionCts.Token));
                            break;
                        case ServerMessageKind.Join:
                            Emit(ClientEventKind.Info, "room: member " + msg.Join.Member + " joined" + (msg.Join.Publish ? " (" + msg.Join.Count + " Gaussians); its avatar follows" : " (watching)"));
                            _frames.Drop(msg.Join.Member); // a repeated join (the room healed): the old avatar's frames are void
                            if (!msg.Join.Publish) _roomEvents.Enqueue(new RoomEvent { Kind = RoomEventKind.Joined, Member = msg.Join.Member, Join = msg.Join, Session = session });
                            break;
                        case ServerMessageKind.Leave:
                            if (conn.LeftMember != null)
                            {
                                _frames.Drop(conn.LeftMember.Id);
                                _roomEvents.Enqueue(new RoomEvent { Kind = RoomEventKind.Left, Member = conn.LeftMember.Id, Reason = msg.Leave.Reason, Session = session });
                            }
                            break;
                        case ServerMessageKind.Avatar:
                        case ServerMessageKind.Rig: // params sessions (PROTOCOL.md 13): the rig completes an avatar
                            if (conn.CompletedMember != null)
                            {
                                MemberState ms = conn.CompletedMember;
                                _roomEvents.Enqueue(new RoomEvent { Kind = RoomEventKind.Joined, Member = ms.Id, Avatar = ms.Avatar, Join = ms.Join, Welcome = conn.Welcome.ForMember(ms.Join), Session = session });
                            }
                            else if (conn.State == ClientState.Streaming && ((kind == ServerMessageKind.Rig ? msg.Rig.Member : msg.Avatar.Member) == null || !conn.InRoom))
                            {
                                lock (_avatarLock)
                                {
                                    _pendingAvatar = conn.Avatar;
                                    _pendingWelcome = conn.Welcome;
                                    _pendingSession = session;
                                }
                                rxToken = sessionCts.Token; // handshake done: no more deadline
                                if (!handshakeDone) handshakeCts.Dispose();
                                handshakeDone = true;
                                SetStatus(ClientStatus.Streaming, "streaming");
                            }
                            break;
                        case ServerMessageKind.Frame:
                            {
                                FrameData f = msg.Frame;
                                long now = OferaClock.NowMicros();
                                f.ReceivedAt = now;
                                f.SessionNumber = session;
                                Interlocked.Increment(ref Stats.FramesReceived);
                                if (f.Member == null)
                                {
                                    // t and seq are this client's own only for its own stream; params frames carry them
                                    // only when stamped (about once a second: PROTOCOL.md 13.5), so no seq gaps there
                                    if (f.Stamped)
                                    {
                                        Stats.RoundTrip.Add(now - f.T);
                                        long total = f.Timing("total");
                                        if (total >= 0) Stats.ServerTotal.Add(total);
                                    }
                                    if (!f.HasParams && lastSeq >= 0 && f.Seq > lastSeq + 1) Interlocked.Add(ref Stats.FramesSkippedByServer, f.Seq - lastSeq - 1);
                                    if (f.Stamped) lastSeq = f.Seq;
                                }
                                DeltaState ds = f.Member == null && conn.Format != null ? conn.Format.Delta : null;
                                if (ds != null) // delta session: a frame replacing an untaken one must carry everything
                                {
                                    ds.Track(f);
                                    if (f.HasIndex && _frames.HasUntaken(null)) ds.FillDense(f);
                                }
                                if (_frames.Publish(f.Member)) Interlocked.Increment(ref Stats.FramesDropped);
                                break;
                            }
                        case ServerMessageKind.Error:
                            {
                                ErrorMessage err = msg.Error;
                                Interlocked.Increment(ref Stats.ServerErrors);
                                Emit(ClientEventKind.ServerError, "server error " + err, err);
                                if (err.Fatal)
                                {
                                    end.Reason = err.Code;
                                    end.Permanent = ErrorCodes.IsConfigurationError(err.Code);
                                }
                                break;
                            }
                        case ServerMessageKind.Pong:
                            Stats.PingRoundTrip.Add(OferaClock.NowMicros() - msg.PongT);
                            break;
                    }
                }
            }
            finally
            {
                sessionCts.Cancel();
                if (sender != null)
                {
                    try { await sender.ConfigureAwait(false); } catch (Exception) { }
                }
                if (ws.State == WebSocketState.Open) await CloseQuietly(ws, WebSocketCloseStatus.NormalClosure, "").ConfigureAwait(false);
                _currentWs = null;
                ws.Dispose();
                sessionCts.Dispose();
            }
        }

        static async Task CloseQuietly(ClientWebSocket ws, WebSocketCloseStatus code, string reason)
        {
            try
            {
                using (CancellationTokenSource t = new CancellationTokenSource(1000))
                    await ws.CloseOutputAsync(code, reason, t.Token).ConfigureAwait(false);
            }
            catch (Exception) { try { ws.Abort(); } catch (Exception) { } }
        }

        /// <summary>Reads one whole message into the pooled buffer (grown as needed, up to the limit). -1: closed.</summary>
        async Task<int> ReceiveMessageAsync(ClientWebSocket ws, ClientConnection conn, CancellationToken ct)
        {
            int filled = 0;
            while (true)
            {
                if (filled == _rx.Length)
                {
                    if (_rx.Length >= _opt.MaxMessageSize)
                    {
                        await CloseQuietly(ws, WebSocketCloseStatus.MessageTooBig, ErrorCodes.MessageTooLarge).ConfigureAwait(false);
                        throw new ProtocolException(ErrorCodes.MessageTooLarge, "a server message exceeds " + _opt.MaxMessageSize + " bytes");
                    }
                    byte[] bigger = new byte[(int)Math.Min((long)_rx.Length * 2, _opt.MaxMessageSize)];
                    Buffer.BlockCopy(_rx, 0, bigger, 0, filled);
                    _rx = bigger;
                }
                WebSocketReceiveResult r = await ws.ReceiveAsync(new ArraySegment<byte>(_rx, filled, _rx.Length - filled), ct).ConfigureAwait(false);
                if (r.MessageType == WebSocketMessageType.Close) return -1;
                if (r.MessageType == WebSocketMessageType.Text)
                {
                    ProtocolException e = conn.ReceiveText();
                    await CloseQuietly(ws, (WebSocketCloseStatus)e.CloseCode, e.Code).ConfigureAwait(false);
                    throw e;
                }
                filled += r.Count;
                if (r.EndOfMessage) return filled;
            }
        }

        async Task SendLoopAsync(ClientWebSocket ws, ClientConnection conn, CancellationToken ct)
        {
            MsgPackWriter w = new MsgPackWriter(512);
            float[] sample = new float[_layoutLength];
            long seq = 0;
            long pingEvery = (long)(_opt.PingIntervalSeconds * 1e6);
            long nextPing = OferaClock.NowMicros() + pingEvery;
            try
            {
                while (!ct.IsCancellationRequested)
                {
                    int waitMs = -1;
                    if (pingEvery > 0) waitMs = (int)Math.Max(0, (nextPing - OferaClock.NowMicros()) / 1000);
                    bool signalled = await _sendSignal.WaitAsync(waitMs, ct).ConfigureAwait(false);
                    if (_byeRequested)
                    {
                        w.Clear();
                        ClientMessageEncoder.Bye(w);
                        await ws.SendAsync(w.Segment, WebSocketMessageType.Binary, true, ct).ConfigureAwait(false);
                        return;
                    }
                    byte[] raw;
                    while (_raw.TryDequeue(out raw))
                        await ws.SendAsync(new ArraySegment<byte>(raw), WebSocketMessageType.Binary, true, ct).ConfigureAwait(false);
                    if (signalled)
                    {
                        bool have;
                        long t;
                        lock (_bsLock)
                        {
                            have = _bsPending;
                            _bsPending = false;
                            t = _bsT;
                            if (have) Array.Copy(_bsLatest, sample, _layoutLength);
                        }
                        if (have)
                        {
                            conn.EncodeBs(seq++, t, sample, w);
                            await ws.SendAsync(w.Segment, WebSocketMessageType.Binary, true, ct).ConfigureAwait(false);
                            Interlocked.Increment(ref Stats.BsSent);
                        }
                    }
                    if (pingEvery > 0 && OferaClock.NowMicros() >= nextPing)
                    {
                        conn.EncodePing(OferaClock.NowMicros(), w);
                        await ws.SendAsync(w.Segment, WebSocketMessageType.Binary, true, ct).ConfigureAwait(false);
                        nextPing = OferaClock.NowMicros() + pingEvery;
                    }
                }
            }
            catch (OperationCanceledException) { }
            catch (WebSocketException) { } // the receive loop sees the same failure and ends the session
            catch (ObjectDisposedException) { }
            catch (InvalidOperationException) { } // connection closed under us (fatal error received)
        }
    }
}
