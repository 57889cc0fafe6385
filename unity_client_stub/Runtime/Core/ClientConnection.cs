// Sans-I/O client end of one session (PROTOCOL.md section 3): state machine, avatar assembly,
// frame decoding. The caller owns the socket. UnityEngine-free, C# 7.2.
using System;

namespace Ofera.Client
{
    public enum ClientState { Idle, AwaitingWelcome, ReceivingAvatar, Streaming, Closed }

    /// <summary>
    /// One session's protocol state. Not thread-safe: one receiving thread calls <see cref="Receive"/>;
    /// encoders write into caller-owned writers so sending may happen on another thread.
    /// </summary>
    public sealed class ClientConnection
    {
        readonly ServerMessageDecoder _decoder = new ServerMessageDecoder();
        int _nextChunk, _nextOffset, _totalChunks = -1;

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

        /// <summary>Encodes `hello` into <paramref name="w"/> (cleared first) and moves to AwaitingWelcome.</summary>
        public void EncodeHello(Hello h, MsgPackWriter w)
        {
            if (State != ClientState.Idle) throw new InvalidOperationException("hello may be sent once, first");
            if (Protocol.LayoutLength(h.Layout) < 0) throw new ArgumentException("unknown layout '" + h.Layout + "'; expected one of " + string.Join(", ", Protocol.Layouts));
            if (h.Encoding != null && !Protocol.Contains(Protocol.Encodings, h.Encoding)) throw new ArgumentException("unknown encoding '" + h.Encoding + "'; expected one of " + string.Join(", ", Protocol.Encodings));
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
            try
            {
                ServerMessageKind kind = _decoder.Decode(buf, offset, count, Format, result, MaxMessageSize);
                Advance(buf, result);
                return kind;
            }
            catch (ProtocolException e)
            {
                ProtocolException err = State != ClientState.Streaming ? e.AsFatal() : e;
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
                        Mirroring = MirrorFlameToUnity && w.Coords == "flame";
                        Avatar = new AvatarData(w.Count, w.ShDegree);
                        _nextChunk = 0; _nextOffset = 0; _totalChunks = -1;
                        State = ClientState.ReceivingAvatar;
                        break;
                    }
                case ServerMessageKind.Avatar:
                    {
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
                            State = ClientState.Streaming;
                        }
                        break;
                    }
                case ServerMessageKind.Frame:
                    if (State != ClientState.Streaming)
                        throw new ProtocolException(ErrorCodes.NotReady, "frame before the avatar was complete (state " + State + ")");
                    if (Mirroring) Coords.MirrorX(m.Frame);
                    break;
                case ServerMessageKind.Error:
                    if (m.Error.Fatal) State = ClientState.Closed;
                    break;
            }
        }
    }
}
