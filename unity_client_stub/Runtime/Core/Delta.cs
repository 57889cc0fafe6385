// Temporal delta frames (PROTOCOL.md 7.1): the codes a delta-session client holds, and the decoder of key and
// delta frames (a part of ServerMessageDecoder, Codec.cs). Mirrors ofera_protocol/delta.py's DeltaDecoder: a
// delta frame is checked whole before anything changes. UnityEngine-free, C# 7.2.
using System;

namespace Ofera.Client
{
    /// <summary>
    /// The wire codes of every Gaussian of a delta session (q13: uint16 x 3, uint32, uint8 x 3; f16: the halves'
    /// bits), kept in wire layout (little-endian bytes). Key frames replace them all; delta frames the changed
    /// ones. One per session (FrameFormat.Delta); after a failed delta frame the client sends `resync`.
    /// </summary>
    public sealed class DeltaState
    {
        public readonly FrameEncoding Encoding;
        public readonly int Count;
        public readonly Quant Quant;
        public readonly int PosBytes, RotBytes, ScaleBytes;
        public readonly byte[] PositionCodes, RotationCodes, ScaleCodes;
        /// <summary>False until the first key frame: a delta frame before it is not_ready.</summary>
        public bool HasKey;
        /// <summary>Set when a frame of this session could not be applied: send `resync` (ClientMessageEncoder.Resync).</summary>
        public bool ResyncNeeded;
        byte[] _pos = new byte[0], _rot = new byte[0], _scale = new byte[0];
        uint[] _changed = new uint[0];
        bool[] _wide = new bool[0], _mp = new bool[0], _mr = new bool[0], _ms = new bool[0];

        public DeltaState(FrameEncoding encoding, int count, Quant quant)
        {
            if (encoding != FrameEncoding.Q13 && encoding != FrameEncoding.F16)
                throw new ArgumentException("delta frames exist in f16 and q13 only, not " + Protocol.EncodingName(encoding));
            if (encoding == FrameEncoding.Q13 && quant == null) throw new ArgumentNullException("quant");
            Encoding = encoding;
            Count = count;
            Quant = quant;
            Protocol.FieldBytes(encoding, out PosBytes, out RotBytes, out ScaleBytes);
            PositionCodes = new byte[(long)count * PosBytes];
            RotationCodes = new byte[(long)count * RotBytes];
            ScaleCodes = new byte[(long)count * ScaleBytes];
        }

        internal void Grow(int n)
        {
            if (_changed.Length >= n) return;
            _changed = new uint[n];
            _wide = new bool[n]; _mp = new bool[n]; _mr = new bool[n]; _ms = new bool[n];
            _pos = new byte[6L * n];
            _rot = new byte[(long)RotBytes * n];
            _scale = new byte[(long)ScaleBytes * n];
        }

        float[] _fullPos, _fullRot, _fullScale;

        /// <summary>
        /// Keeps every Gaussian's latest values (as the application receives them, after any mirroring) from the
        /// session's frames; call for each frame in arrival order (OferaClient does). A consumer that may miss
        /// frames (newest-wins hand-off to the main thread) must get <see cref="FillDense"/> instead of a delta
        /// frame whose predecessor it never took: the Gaussians that frame changed would stay stale.
        /// </summary>
        public void Track(FrameData f)
        {
            if (!f.HasValues) return;
            if (_fullPos == null)
            {
                _fullPos = new float[3L * Count]; _fullRot = new float[4L * Count]; _fullScale = new float[3L * Count];
            }
            if (!f.HasIndex)
            {
                Array.Copy(f.Position, _fullPos, 3 * f.N);
                Array.Copy(f.Rotation, _fullRot, 4 * f.N);
                Array.Copy(f.Scale, _fullScale, 3 * f.N);
                return;
            }
            for (int j = 0; j < f.N; j++)
            {
                int i = (int)f.Index[j];
                Array.Copy(f.Position, 3 * j, _fullPos, 3 * i, 3);
                Array.Copy(f.Rotation, 4 * j, _fullRot, 4 * i, 4);
                Array.Copy(f.Scale, 3 * j, _fullScale, 3 * i, 3);
            }
        }

        /// <summary>Turns <paramref name="f"/> (a tracked frame) into a dense frame of every Gaussian's latest values.</summary>
        public void FillDense(FrameData f)
        {
            if (_fullPos == null) return;
            f.EnsureCapacity(Count);
            Array.Copy(_fullPos, f.Position, 3 * Count);
            Array.Copy(_fullRot, f.Rotation, 4 * Count);
            Array.Copy(_fullScale, f.Scale, 3 * Count);
            f.N = Count;
            f.HasIndex = false;
            f.HasValues = true;
        }

        internal uint[] Changed { get { return _changed; } }
        internal bool[] Wide { get { return _wide; } }
        internal bool[] MovedPosition { get { return _mp; } }
        internal bool[] MovedRotation { get { return _mr; } }
        internal bool[] MovedScale { get { return _ms; } }
        internal byte[] NewPositions { get { return _pos; } }
        internal byte[] NewRotations { get { return _rot; } }
        internal byte[] NewScales { get { return _scale; } }
    }

    public sealed partial class ServerMessageDecoder
    {
        /// <summary>A frame of a delta session into <paramref name="f"/>: a key frame (dense, IsKey) or a delta frame
        /// (HasIndex: the changed Gaussians, with their new absolute values). Throws ProtocolException; the held
        /// codes are unchanged then.</summary>
        void DecodeDeltaSessionFrame(FrameFormat fmt, FrameData f)
        {
            const string w = "frame";
            DeltaState d = fmt.Delta;
            try
            {
                bool key = GetBool(Top, Keys.Key, w);
                if (key) DecodeKeyFrame(fmt, d, f);
                else DecodeDelta(fmt, d, f);
            }
            catch (ProtocolException)
            {
                d.ResyncNeeded = true;
                throw;
            }
        }

        void DecodeKeyFrame(FrameFormat fmt, DeltaState d, FrameData f)
        {
            const string w = "frame";
            if (Present(Top, Keys.Index)) throw Err(ErrorCodes.BadField, "frame: a key frame is dense (no 'index')");
            bool values = DecodeValues;
            DecodeValues = true;
            try { DecodeFrame(fmt, f); } // every check of a dense frame; the codes are then taken as they are
            finally { DecodeValues = values; }
            int pOff, pLen, rOff, rLen, sOff, sLen;
            GetBin(Top, Keys.Position, w, true, out pOff, out pLen);
            GetBin(Top, Keys.Rotation, w, true, out rOff, out rLen);
            GetBin(Top, Keys.Scale, w, true, out sOff, out sLen);
            byte[] b = R.Buffer;
            Buffer.BlockCopy(b, pOff, d.PositionCodes, 0, pLen);
            Buffer.BlockCopy(b, rOff, d.RotationCodes, 0, rLen);
            Buffer.BlockCopy(b, sOff, d.ScaleCodes, 0, sLen);
            d.HasKey = true;
            f.IsKey = true;
        }

        /// <summary>Set bits of a PROTOCOL.md 7.1 bitmask over n entries (LSB first) into ids; returns how many.</summary>
        int MaskIds(int k, long n, uint[] ids, bool[] flags)
        {
            const string w = "frame";
            int off, len;
            GetBin(Top, k, w, true, out off, out len);
            if (len != (n + 7) / 8)
                throw Err(ErrorCodes.BadLength, "frame: '" + Keys.Names[k] + "' has " + len + " bytes, a mask of " + n + " needs " + ((n + 7) / 8));
            byte[] b = R.Buffer;
            int m = 0;
            for (int i = 0; i < len; i++)
            {
                int v = b[off + i];
                for (int bit = 0; v != 0 && bit < 8; bit++, v >>= 1)
                {
                    if ((v & 1) == 0) continue;
                    long id = 8L * i + bit;
                    if (id >= n) throw Err(ErrorCodes.BadField, "frame: '" + Keys.Names[k] + "' has bits set beyond its " + n + " entries");
                    if (ids != null)
                    {
                        if (m >= ids.Length) throw Err(ErrorCodes.BadField, "frame: 'changed' marks more Gaussians than n");
                        ids[m] = (uint)id;
                    }
                    else flags[id] = true;
                    m++;
                }
            }
            return m;
        }

        void DecodeDelta(FrameFormat fmt, DeltaState d, FrameData f)
        {
            const string w = "frame";
            if (!d.HasKey) throw Err(ErrorCodes.NotReady, "frame: a delta frame before any key frame (send resync)");
            long seq = GetInt(Top, Keys.Seq, w, 0, long.MaxValue);
            long t = GetInt(Top, Keys.T, w, long.MinValue, long.MaxValue);
            long nl = GetInt(Top, Keys.N, w, 0, Protocol.UInt32Max);
            if (nl > d.Count) throw Err(ErrorCodes.BadField, "frame: n = " + nl + " is more than the avatar's " + d.Count);
            int n = (int)nl;
            d.Grow(n);
            uint[] ids = d.Changed;
            int marked = MaskIds(Keys.Changed, d.Count, ids, null);
            if (marked != n) throw Err(ErrorCodes.BadField, "frame: n = " + n + " but 'changed' marks " + marked + " Gaussians");
            bool[] mp = d.MovedPosition, mr = d.MovedRotation, ms = d.MovedScale, wide = d.Wide;
            Array.Clear(mp, 0, n); Array.Clear(mr, 0, n); Array.Clear(ms, 0, n); Array.Clear(wide, 0, n);
            int np = MaskIds(Keys.MovedPosition, n, null, mp);
            int nr = MaskIds(Keys.MovedRotation, n, null, mr);
            int ns = MaskIds(Keys.MovedScale, n, null, ms);
            for (int j = 0; j < n; j++)
                if (!mp[j] && !mr[j] && !ms[j]) throw Err(ErrorCodes.BadField, "frame: a changed Gaussian carries nothing");
            int nw = MaskIds(Keys.Wide, np, null, wide);
            int dOff, pOff, rOff, sOff;
            string enc = Protocol.EncodingName(d.Encoding);
            GetArray(Top, Keys.PositionDelta, w, 3, np - nw, true, out dOff, "int8 x 3");
            GetArray(Top, Keys.Position, w, d.PosBytes, nw, true, out pOff, enc + " position");
            GetArray(Top, Keys.Rotation, w, d.RotBytes, nr, true, out rOff, enc + " rotation");
            GetArray(Top, Keys.Scale, w, d.ScaleBytes, ns, true, out sOff, enc + " scale");
            byte[] b = R.Buffer;
            byte[] pos = d.NewPositions, rot = d.NewRotations, scl = d.NewScales;
            int rbytes = d.RotBytes, sbytes = d.ScaleBytes;
            // the carried Gaussians' codes after this frame (held codes, then what it carries), checked, not yet held
            for (int j = 0, p = 0, narrow = 0, whole = 0, r = 0, s = 0; j < n; j++)
            {
                int i = (int)ids[j];
                Buffer.BlockCopy(d.PositionCodes, 6 * i, pos, 6 * j, 6);
                Buffer.BlockCopy(d.RotationCodes, rbytes * i, rot, rbytes * j, rbytes);
                Buffer.BlockCopy(d.ScaleCodes, sbytes * i, scl, sbytes * j, sbytes);
                if (mp[j])
                {
                    int o = 6 * j;
                    if (wide[p++])
                    {
                        Buffer.BlockCopy(b, pOff + 6 * whole, pos, o, 6);
                        whole++;
                    }
                    else
                    {
                        for (int c = 0; c < 3; c++)
                        {
                            int held = pos[o + 2 * c] | (pos[o + 2 * c + 1] << 8);
                            int v = held + (sbyte)b[dOff + 3 * narrow + c];
                            if (v < 0 || v > 65535) throw Err(ErrorCodes.BadField, "frame: 'position_delta' takes a code outside 0..65535");
                            pos[o + 2 * c] = (byte)v;
                            pos[o + 2 * c + 1] = (byte)(v >> 8);
                        }
                        narrow++;
                    }
                }
                if (mr[j]) Buffer.BlockCopy(b, rOff + rbytes * r++, rot, rbytes * j, rbytes);
                if (ms[j]) Buffer.BlockCopy(b, sOff + sbytes * s++, scl, sbytes * j, sbytes);
            }
            f.EnsureCapacity(n);
            switch (d.Encoding) // decode first (f16: refuses NaN / infinity), then hold
            {
                case FrameEncoding.Q13:
                    FrameCodec.DecodeQ13Positions(pos, 0, n, d.Quant, f.Position, 0);
                    FrameCodec.DecodeQ13Rotations(rot, 0, n, f.Rotation, 0);
                    FrameCodec.DecodeQ13Scales(scl, 0, n, d.Quant, f.Scale, 0);
                    break;
                default:
                    if (!FrameCodec.DecodeF16(pos, 0, 3 * n, f.Position, 0)) throw Err(ErrorCodes.NonFinite, "frame: a position holds NaN or infinity");
                    if (!FrameCodec.DecodeF16(rot, 0, 4 * n, f.Rotation, 0)) throw Err(ErrorCodes.NonFinite, "frame field 'rotation' holds NaN or infinity");
                    if (!FrameCodec.DecodeF16(scl, 0, 3 * n, f.Scale, 0)) throw Err(ErrorCodes.NonFinite, "frame field 'scale' holds NaN or infinity");
                    break;
            }
            DecodeTiming(f);
            for (int j = 0; j < n; j++)
            {
                int i = (int)ids[j];
                Buffer.BlockCopy(pos, 6 * j, d.PositionCodes, 6 * i, 6);
                Buffer.BlockCopy(rot, rbytes * j, d.RotationCodes, rbytes * i, rbytes);
                Buffer.BlockCopy(scl, sbytes * j, d.ScaleCodes, sbytes * i, sbytes);
                f.Index[j] = ids[j];
            }
            f.Seq = seq;
            f.T = t;
            f.N = n;
            f.HasIndex = true;
            f.IsKey = false;
            f.HasValues = true;
            f.Payload.Length = 0;
        }
    }
}
