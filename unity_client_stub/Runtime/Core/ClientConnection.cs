// Sans-I/O client end of one session (PROTOCOL.md section 3): state machine, avatar assembly,
// frame decoding. The caller owns the socket. UnityEngine-free, C# 7.2.
using System;
using System.Collections.Generic;

namespace Ofera.Client
{
    /// <summary>ReceivingRig: params sessions only (PROTOCOL.md 13.2), between the last avatar chunk and the complete rig.</summary>
    public enum ClientState { Idle, AwaitingWelcome, ReceivingAvatar, ReceivingRig, Streaming, Closed }

    /// <summary>
    /// One session's protocol state. Not thread-safe: one receiving thread calls <see cref="Receive"/>;
    /// encoders write into caller-owned writers so sending may happen on another thread.
    /// </summary>
    public sealed class ClientConnection : IFrameFormatSource
    {
        readonly ServerMessageDecoder _decoder = new ServerMessageDecoder();
        int _nextChunk, _nextOffset, _totalChunks = -1;
        readonly Dictionary<string, MemberState> _members = new Dictionary<string, MemberState>();
        readonly RigDecoder _rigDecoder = new RigDecoder();
        RigAssembler _rig;
        RigDeformer _deformer;

        /// <summary>Keep frames' wire arrays (FrameData.Payload) for the GPU upload path; with DecodeValues false, skip the float decode.</summary>
        public bool KeepPayload { get { return _decoder.KeepPayload; } set { _decoder.KeepPayload = value; } }
        public bool DecodeValues { get { return _decoder.DecodeValues; } set { _decoder.DecodeValues = value; } }

        /// <summary>True when welcome named a room (PROTOCOL.md 12): the session streams from welcome on, and every avatar
        /// (one's own too, with Self) comes with a join; its chunks and frames carry `member` and are routed per member.</summary>
        public bool InRoom { get { return Welcome != null && Welcome.Room != null; } }
        /// <summary>Set by the Receive call whose avatar chunk completed a member's avatar (else null).</summary>
        public MemberState CompletedMember { get; private set; }
        /// <summary>Set by the Receive call that handled a `leave` for a known member (else null).</summary>
        public MemberState LeftMember { get; private set; }
        public int MemberCount { get { return _members.Count; } }

        /// <summary>A member announced by `join` (its avatar may still be arriving), or null.</summary>
        public MemberState Member(string id)
        {
            MemberState m;
            return id != null && _members.TryGetValue(id, out m) ? m : null;
        }

        /// <summary>IFrameFormatSource: the format of a member whose avatar is complete, else null (the frame is not_ready).</summary>
        public FrameFormat FormatFor(string member)
        {
            MemberState m = Member(member);
            return m != null && m.Complete ? m.Format : null;
        }

        public ClientState State { get; private set; }
        public Hello SentHello { get; private set; }
        public Welcome Welcome { get; private set; }
        public FrameFormat Format { get; private set; }
        /// <summary>The avatar being assembled (complete once State is Streaming).</summary>
        public AvatarData Avatar { get; private set; }
        /// <summary>Largest message accepted (bytes).</summary>
        public int MaxMessageSize = Protocol.MaxServerMessage;
        /// <summary>If the session runs in FLAME coordinates, mirror avatar and frames to Unity's on receipt.</summary>
        public bool MirrorFlameToUnity;
        /// <summary>True when received data is being mirrored (welcome said flame and MirrorFlameToUnity is set).</summary>
        public bool Mirroring { get; private set; }
        /// <summary>Params sessions: the rig (complete once State is Streaming; also Avatar.Rig), else null.</summary>
        public RigData Rig { get; private set; }
        /// <summary>Params sessions: what the client's own deformation is mirrored by (x): coords unity (PROTOCOL.md 13.4
        /// step 8) or Mirroring; the GPU path applies the same.</summary>
        public bool MirrorDeformed { get; private set; }

        /// <summary>Encodes `hello` into <paramref name="w"/> (cleared first) and moves to AwaitingWelcome.</summary>
        public void EncodeHello(Hello h, MsgPackWriter w)
        {
            if (State != ClientState.Idle) throw new InvalidOperationException("hello may be sent once, first");
            if (Protocol.LayoutLength(h.Layout) < 0) throw new ArgumentException("unknown layout '" + h.Layout + "'; expected one of " + string.Join(", ", Protocol.Layouts));
            if (h.Encoding != null && !Protocol.Contains(ParamsProtocol.HelloEncodings, h.Encoding)) throw new ArgumentException("unknown encoding '" + h.Encoding + "'; expected one of " + string.Join(", ", ParamsProtocol.HelloEncodings));
            if (h.Coords != null && !Protocol.Contains(Protocol.CoordsNames, h.Coords)) throw new ArgumentException("unknown coords '" + h.Coords + "'; expected one of flame, unity");
            w.Clear();
            ClientMessageEncoder.Hello(w, h);
            if (w.Length > Protocol.MaxClientMessage) throw new ArgumentException("hello exceeds 64 KiB (token too long?)");
            SentHello = h;
            State = ClientState.AwaitingWelcome;
        }

        /// <summary>Encodes a `bs` of the session's layout length into <paramref name="w"/> (cleared first).</summary>
        public void EncodeBs(long seq, long t, float[] weights, MsgPackWriter w)
        {
            if (State != ClientState.ReceivingAvatar && State != ClientState.Streaming)
                throw new InvalidOperationException("bs needs a welcome first (state " + State + ")");
            int n = Protocol.LayoutLength(SentHello.Layout);
            if (weights.Length < n) throw new ArgumentException("layout " + SentHello.Layout + " needs " + n + " weights, got " + weights.Length);
            w.Clear();
            ClientMessageEncoder.Bs(w, seq, t, weights, n);
        }

        public void EncodePing(long t, MsgPackWriter w)
        {
            w.Clear();
            ClientMessageEncoder.Ping(w, t);
        }

        public void EncodeBye(MsgPackWriter w)
        {
            w.Clear();
            ClientMessageEncoder.Bye(w);
            State = ClientState.Closed;
        }

        /// <summary>Marks the connection closed (socket gone).</summary>
        public void Close() { State = ClientState.Closed; }

        /// <summary>
        /// Decodes one binary message and advances the state. Frames are decoded into result.Frame.
        /// Throws <see cref="ProtocolException"/>: fatal before streaming starts (and for always-fatal
        /// codes); a bad frame while streaming is non-fatal (drop it, carry on).
        /// </summary>
        public ServerMessageKind Receive(byte[] buf, int offset, int count, ServerMessage result)
        {
            if (State == ClientState.Closed) throw new InvalidOperationException("receive on a closed connection");
            CompletedMember = null;
            LeftMember = null;
            try
            {
                ServerMessageKind kind = _decoder.Decode(buf, offset, count, Format, result, MaxMessageSize);
                Advance(buf, result);
                return kind;
            }
            catch (ProtocolException e)
            {
                // a bad message while streaming (a room session: from welcome on) costs that message only
                ProtocolException err = State == ClientState.Streaming ? e : e.AsFatal();
                if (err.Fatal) State = ClientState.Closed;
                throw err;
            }
        }

        /// <summary>A WebSocket text message: always fatal (text_frame, close 1003).</summary>
        public ProtocolException ReceiveText()
        {
            State = ClientState.Closed;
            return new ProtocolException(ErrorCodes.TextFrame, "the server sent a text message; only binary messages are allowed", true);
        }

        void Advance(byte[] buf, ServerMessage m)
        {
            switch (m.Kind)
            {
                case ServerMessageKind.Welcome:
                    {
                        if (State != ClientState.AwaitingWelcome)
                            throw new ProtocolException(ErrorCodes.NotReady, "unexpected welcome in state " + State, true);
                        Welcome w = m.Welcome;
                        string coords = SentHello.Coords ?? "flame";
                        if (w.Layout != SentHello.Layout || w.Coords != coords)
                            throw new ProtocolException(ErrorCodes.BadField, "welcome's layout/coords (" + w.Layout + "/" + w.Coords + ") differ from hello's (" + SentHello.Layout + "/" + coords + ")", true);
                        Welcome = w;
                        Format = w.ToFormat();
                        _members.Clear();
                        _decoder.MemberFormats = w.Room != null ? this : null;
                        Mirroring = MirrorFlameToUnity && w.Coords == "flame";
                        MirrorDeformed = w.Coords == "unity" || Mirroring;
                        Rig = null; _deformer = null;
                        _rig = Format.Params ? new RigAssembler() : null;
                        Avatar = new AvatarData(w.Count, w.ShDegree); // a room's: never assembled (it comes with a join)
                        _nextChunk = 0; _nextOffset = 0; _totalChunks = -1;
                        State = w.Room != null ? ClientState.Streaming : ClientState.ReceivingAvatar;
                        break;
                    }
                case ServerMessageKind.Join:
                    {
                        if (Welcome == null) throw new ProtocolException(ErrorCodes.NotReady, "join before welcome", true);
                        JoinMessage j = m.Join;
                        MemberState ms = new MemberState();
                        ms.Id = j.Member;
                        ms.Join = j;
                        _members.Remove(j.Member); // a repeated join replaces the member (new avatar follows)
                        if (j.Publish) // a watch-only member has no avatar and no frames
                        {
                            ms.Avatar = new AvatarData(j.Count, j.ShDegree);
                            Quant q = j.Quant ?? Welcome.Quant;
                            FrameEncoding enc = Format.Encoding;
                            if (enc == FrameEncoding.Q13 && q == null)
                                throw new ProtocolException(ErrorCodes.BadField, "join: q13 session without quant parameters for member '" + j.Member + "'");
                            ms.Format = new FrameFormat(enc, j.Count, Format.Sparse, enc == FrameEncoding.Q13 ? q : null) { Params = Format.Params };
                            if (Format.Params) ms.RigParts = new RigAssembler();
                        }
                        _members[j.Member] = ms;
                        break;
                    }
                case ServerMessageKind.Leave:
                    {
                        MemberState ms;
                        if (_members.TryGetValue(m.Leave.Member, out ms))
                        {
                            _members.Remove(m.Leave.Member);
                            LeftMember = ms;
                        }
                        break;
                    }
                case ServerMessageKind.Avatar:
                    {
                        if (InRoom)
                        {
                            if (m.Avatar.Member == null) throw new ProtocolException(ErrorCodes.BadField, "an avatar chunk without 'member' in a room session");
                            MemberChunk(buf, m.Avatar);
                            break;
                        }
                        if (State != ClientState.ReceivingAvatar)
                            throw new ProtocolException(ErrorCodes.NotReady, "unexpected avatar chunk in state " + State, true);
                        AvatarChunkHeader h = m.Avatar;
                        string problems = "";
                        if (h.Count != Avatar.Count) problems += "; count " + h.Count + " != welcome's " + Avatar.Count;
                        if (h.ShDegree != Avatar.ShDegree) problems += "; sh_degree " + h.ShDegree + " != welcome's " + Avatar.ShDegree;
                        if (h.Chunk != _nextChunk) problems += "; chunk " + h.Chunk + " arrived, expected " + _nextChunk;
                        if (_totalChunks >= 0 && h.Chunks != _totalChunks) problems += "; chunks " + h.Chunks + " != " + _totalChunks + " announced before";
                        if (h.Offset != _nextOffset) problems += "; offset " + h.Offset + " != " + _nextOffset;
                        bool last = h.Chunk == h.Chunks - 1;
                        if (last && h.Offset + h.N != Avatar.Count) problems += "; last chunk ends at " + (h.Offset + h.N) + ", avatar has " + Avatar.Count;
                        if (problems.Length > 0)
                            throw new ProtocolException(ErrorCodes.BadField, "bad avatar chunk: " + problems.Substring(2), true);
                        _decoder.CopyAvatarChunk(buf, Avatar);
                        _totalChunks = h.Chunks;
                        _nextChunk++;
                        _nextOffset += h.N;
                        if (last)
                        {
                            if (Mirroring) Coords.MirrorX(Avatar);
                            State = Format.Params ? ClientState.ReceivingRig : ClientState.Streaming;
                        }
                        break;
                    }
                case ServerMessageKind.Rig:
                    if (m.Rig.Member != null && InRoom) { MemberRig(buf, m.Rig); break; }
                    if (State != ClientState.ReceivingRig)
                        throw new ProtocolException(ErrorCodes.NotReady, "unexpected rig chunk in state " + State, true);
                    if (Welcome.RigBytes.HasValue && m.Rig.Size != Welcome.RigBytes) // optional on decode, as ofera_protocol's
                        throw new ProtocolException(ErrorCodes.BadField, "rig: size " + m.Rig.Size + " != welcome's rig_bytes " + Welcome.RigBytes, true);
                    try
                    {
                        if (!_rig.Add(m.Rig, buf)) break;
                        Rig = DecodeRig(_rig, Avatar.Count, "the avatar");
                    }
                    catch (ProtocolException e) { throw e.AsFatal(); } // the handshake is not over
                    Avatar.Rig = Rig;
                    _deformer = new RigDeformer(Rig);
                    _rig = null;
                    State = ClientState.Streaming;
                    break;
                case ServerMessageKind.Frame:
                    if (State != ClientState.Streaming && !(InRoom && m.Frame.Member != null))
                        throw new ProtocolException(ErrorCodes.NotReady, "frame before the avatar was complete (state " + State + ")");
                    if (m.Frame.HasParams)
                    {
                        RigDeformer d = _deformer;
                        if (m.Frame.Member != null && InRoom) { MemberState fm = Member(m.Frame.Member); d = fm != null ? fm.Deformer : null; }
                        if (DecodeValues && d != null) RigFrames.Deform(d, m.Frame, MirrorDeformed);
                        break;
                    }
                    if (Mirroring && m.Frame.HasValues) Coords.MirrorX(m.Frame);
                    break;
                case ServerMessageKind.Error:
                    if (m.Error.Fatal) State = ClientState.Closed;
                    break;
            }
        }

        void MemberChunk(byte[] buf, AvatarChunkHeader h)
        {
            MemberState ms = Member(h.Member);
            if (ms == null) throw new ProtocolException(ErrorCodes.NotReady, "avatar chunk for member '" + h.Member + "' before its join");
            if (ms.Avatar == null) throw new ProtocolException(ErrorCodes.BadField, "avatar chunk for member '" + h.Member + "', who watches only (no avatar)");
            string problems = "";
            if (ms.Complete) problems += "; the member's avatar is already complete";
            if (h.Count != ms.Avatar.Count) problems += "; count " + h.Count + " != join's " + ms.Avatar.Count;
            if (h.ShDegree != ms.Avatar.ShDegree) problems += "; sh_degree " + h.ShDegree + " != join's " + ms.Avatar.ShDegree;
            if (h.Chunk != ms.NextChunk) problems += "; chunk " + h.Chunk + " arrived, expected " + ms.NextChunk;
            if (ms.TotalChunks >= 0 && h.Chunks != ms.TotalChunks) problems += "; chunks " + h.Chunks + " != " + ms.TotalChunks;
            if (h.Offset != ms.NextOffset) problems += "; offset " + h.Offset + " != " + ms.NextOffset;
            bool last = h.Chunk == h.Chunks - 1;
            if (last && h.Offset + h.N != ms.Avatar.Count) problems += "; last chunk ends at " + (h.Offset + h.N) + ", avatar has " + ms.Avatar.Count;
            if (problems.Length > 0)
            {
                _members.Remove(h.Member); // its stream cannot be shown; a new join starts over
                throw new ProtocolException(ErrorCodes.BadField, "bad avatar chunk for member '" + h.Member + "': " + problems.Substring(2));
            }
            _decoder.CopyAvatarChunk(buf, ms.Avatar);
            ms.TotalChunks = h.Chunks;
            ms.NextChunk++;
            ms.NextOffset += h.N;
            if (last)
            {
                if (Mirroring) Coords.MirrorX(ms.Avatar);
                if (ms.RigParts != null) return; // params: complete with its rig (MemberRig)
                ms.Complete = true;
                CompletedMember = ms;
            }
        }

        /// <summary>Decodes an assembled rig body and checks it against its avatar (fatal bad_field otherwise).</summary>
        RigData DecodeRig(RigAssembler parts, int count, string whose)
        {
            byte[] body = parts.Body;
            RigData rig = _rigDecoder.Decode(body, 0, body.Length);
            if (rig.Count != count) throw new ProtocolException(ErrorCodes.BadField, "rig: count " + rig.Count + " != " + count + " Gaussians of " + whose, true);
            return rig;
        }

        /// <summary>Rooms, params sessions (PROTOCOL.md 13.6): a member's rig chunk; its rig completes the member.</summary>
        void MemberRig(byte[] buf, RigChunkHeader h)
        {
            MemberState ms = Member(h.Member);
            if (ms == null || ms.RigParts == null || ms.NextChunk != ms.TotalChunks)
            {
                if (ms != null) _members.Remove(h.Member); // its stream cannot be shown; a new join starts over
                throw new ProtocolException(ErrorCodes.NotReady, "rig chunk for member '" + h.Member + "' before its join and avatar");
            }
            try
            {
                if (!ms.RigParts.Add(h, buf)) return;
                ms.Rig = DecodeRig(ms.RigParts, ms.Avatar.Count, "member '" + h.Member + "'s avatar");
            }
            catch (ProtocolException e)
            {
                _members.Remove(h.Member);
                throw new ProtocolException(e.Code, e.Detail + " (member '" + h.Member + "')", false); // one member's stream, not the session
            }
            ms.Avatar.Rig = ms.Rig;
            ms.Deformer = new RigDeformer(ms.Rig);
            ms.RigParts = null;
            ms.Complete = true;
            CompletedMember = ms;
        }
    }

    /// <summary>One room member as the connection knows it: its join, its avatar (assembled from chunks) and frame format.</summary>
    public sealed class MemberState
    {
        public string Id;
        public JoinMessage Join;
        public AvatarData Avatar;
        public FrameFormat Format;
        /// <summary>Every avatar chunk arrived: frames for this member are accepted.</summary>
        public bool Complete;
        internal int NextChunk, NextOffset, TotalChunks = -1;
        /// <summary>Params sessions: the member's rig (once complete) and its deformer.</summary>
        public RigData Rig;
        internal RigAssembler RigParts;
        internal RigDeformer Deformer;
    }
}
