// A small msgpack reader and writer for the OFERA protocol: maps, str, int/uint of every width,
// float32/64, bool, nil, bin8/16/32, arrays. Ext types are refused. No allocation except for the
// strings a caller asks for. UnityEngine-free, C# 7.2.
using System;
using System.Text;

namespace Ofera.Client
{
    public enum MsgType { Invalid, Nil, Bool, Int, Float, Str, Bin, Array, Map, Ext }

    /// <summary>
    /// Cursor over one msgpack value in a byte range. <see cref="Validate"/> checks a whole message
    /// (bounds, nesting, key types, limits, UTF-8, trailing bytes) without allocating; the Read methods
    /// then assume the structure is sound and only check the type they are asked for.
    /// </summary>
    public sealed class MsgPackReader
    {
        byte[] _buf;
        int _pos;
        int _end;

        public MsgPackReader() { }
        public MsgPackReader(byte[] buffer, int offset, int count) { Reset(buffer, offset, count); }

        public void Reset(byte[] buffer, int offset, int count)
        {
            if (buffer == null) throw new ArgumentNullException("buffer");
            if (offset < 0 || count < 0 || offset > buffer.Length - count) throw new ArgumentOutOfRangeException("count");
            _buf = buffer;
            _pos = offset;
            _end = offset + count;
        }

        public byte[] Buffer { get { return _buf; } }
        public int Position { get { return _pos; } set { _pos = value; } }
        public int End { get { return _end; } }

        static ProtocolException Malformed(string what) { return new ProtocolException(ErrorCodes.Malformed, "not a valid msgpack message: " + what); }

        // ------------------------------------------------------------------ validation

        /// <summary>
        /// Checks that [offset, offset+count) holds exactly one msgpack map with string keys, nesting at
        /// most <see cref="Protocol.MaxDepth"/>, containers of at most 256 entries, strings of at most
        /// 4096 bytes of valid UTF-8, no ext types, no length prefix beyond the data, no trailing bytes.
        /// Throws <see cref="ProtocolException"/> (malformed) otherwise. Allocates nothing.
        /// </summary>
        public static void Validate(byte[] buf, int offset, int count)
        {
            new MsgPackReader(buf, offset, count).Validate();
        }

        readonly int[] _remaining = new int[Protocol.MaxDepth + 2];
        readonly bool[] _isMapLevel = new bool[Protocol.MaxDepth + 2];

        /// <summary>Validates the reader's whole range (see the static overload); the cursor does not move.</summary>
        public void Validate()
        {
            byte[] buf = _buf;
            int offset = _pos, count = _end - _pos;
            int end = _end;
            if (count <= 0) throw Malformed("empty message");
            byte first = buf[offset];
            bool isMap = (first >= 0x80 && first <= 0x8f) || first == 0xde || first == 0xdf;
            int pos = offset;
            // Explicit stack: remaining items per open container; a map counts keys and values.
            // keyExpected: the next item of this level is a map key (must be a str).
            int[] remaining = _remaining;
            bool[] isMapLevel = _isMapLevel;
            int depth = 0; // number of open containers
            bool top = true;
            while (top || depth > 0)
            {
                if (depth > 0 && remaining[depth] == 0) { depth--; continue; }
                bool keyPosition = false;
                if (depth > 0)
                {
                    keyPosition = isMapLevel[depth] && (remaining[depth] % 2 == 0);
                    remaining[depth]--;
                }
                top = false;
                if (pos >= end) throw Malformed("truncated message");
                byte b = buf[pos++];
                if (keyPosition && !((b >= 0xa0 && b <= 0xbf) || b == 0xd9 || b == 0xda || b == 0xdb))
                    throw Malformed("map key is not a string");
                long len;
                if (b <= 0x7f || b >= 0xe0) continue; // fixint
                if (b >= 0x80 && b <= 0x8f) { OpenContainer(ref depth, remaining, isMapLevel, b & 0x0f, true); continue; }
                if (b >= 0x90 && b <= 0x9f) { OpenContainer(ref depth, remaining, isMapLevel, b & 0x0f, false); continue; }
                if (b >= 0xa0 && b <= 0xbf) { len = b & 0x1f; CheckString(buf, ref pos, end, len); continue; }
                switch (b)
                {
                    case 0xc0: case 0xc2: case 0xc3: continue;
                    case 0xc4: len = Need(buf, ref pos, end, 1); Skip(ref pos, end, len); continue;
                    case 0xc5: len = Need(buf, ref pos, end, 2); Skip(ref pos, end, len); continue;
                    case 0xc6: len = Need(buf, ref pos, end, 4); Skip(ref pos, end, len); continue;
                    case 0xca: Skip(ref pos, end, 4); continue;
                    case 0xcb: Skip(ref pos, end, 8); continue;
                    case 0xcc: case 0xd0: Skip(ref pos, end, 1); continue;
                    case 0xcd: case 0xd1: Skip(ref pos, end, 2); continue;
                    case 0xce: case 0xd2: Skip(ref pos, end, 4); continue;
                    case 0xcf: case 0xd3: Skip(ref pos, end, 8); continue;
                    case 0xd9: len = Need(buf, ref pos, end, 1); CheckString(buf, ref pos, end, len); continue;
                    case 0xda: len = Need(buf, ref pos, end, 2); CheckString(buf, ref pos, end, len); continue;
                    case 0xdb: len = Need(buf, ref pos, end, 4); CheckString(buf, ref pos, end, len); continue;
                    case 0xdc: len = Need(buf, ref pos, end, 2); OpenContainer(ref depth, remaining, isMapLevel, len, false); continue;
                    case 0xdd: len = Need(buf, ref pos, end, 4); OpenContainer(ref depth, remaining, isMapLevel, len, false); continue;
                    case 0xde: len = Need(buf, ref pos, end, 2); OpenContainer(ref depth, remaining, isMapLevel, len, true); continue;
                    case 0xdf: len = Need(buf, ref pos, end, 4); OpenContainer(ref depth, remaining, isMapLevel, len, true); continue;
                    case 0xc1: throw Malformed("byte 0xc1 is never used");
                    default: throw Malformed("ext types are not allowed"); // c7-c9, d4-d8
                }
            }
            if (pos != end) throw Malformed((end - pos) + " trailing bytes after the message");
            if (!isMap) throw new ProtocolException(ErrorCodes.Malformed, "message must be a msgpack map");
        }

        static void OpenContainer(ref int depth, int[] remaining, bool[] isMapLevel, long n, bool map)
        {
            if (n > Protocol.MaxContainerLength) throw Malformed("container of " + n + " entries (at most " + Protocol.MaxContainerLength + ")");
            if (depth + 1 > Protocol.MaxDepth) throw new ProtocolException(ErrorCodes.Malformed, "containers nested deeper than " + Protocol.MaxDepth + " levels");
            depth++;
            remaining[depth] = (int)(map ? 2 * n : n);
            isMapLevel[depth] = map;
        }

        static long Need(byte[] buf, ref int pos, int end, int width)
        {
            if (end - pos < width) throw Malformed("truncated length prefix");
            long v = 0;
            for (int i = 0; i < width; i++) v = (v << 8) | buf[pos + i];
            pos += width;
            return v;
        }

        static void Skip(ref int pos, int end, long n)
        {
            if (n > end - pos) throw Malformed("a length prefix promises " + n + " bytes, " + (end - pos) + " remain");
            pos += (int)n;
        }

        static void CheckString(byte[] buf, ref int pos, int end, long n)
        {
            if (n > Protocol.MaxStringBytes) throw Malformed("string of " + n + " bytes (at most " + Protocol.MaxStringBytes + ")");
            if (n > end - pos) throw Malformed("a string length promises " + n + " bytes, " + (end - pos) + " remain");
            if (!IsValidUtf8(buf, pos, (int)n)) throw Malformed("invalid UTF-8 in a string");
            pos += (int)n;
        }

        /// <summary>Strict UTF-8 check (no overlongs, no surrogates, at most U+10FFFF).</summary>
        public static bool IsValidUtf8(byte[] b, int off, int len)
        {
            int i = off, end = off + len;
            while (i < end)
            {
                int c = b[i];
                if (c < 0x80) { i++; continue; }
                int need; int min;
                if (c >= 0xc2 && c <= 0xdf) { need = 1; min = 0x80; c &= 0x1f; }
                else if (c >= 0xe0 && c <= 0xef) { need = 2; min = 0x800; c &= 0x0f; }
                else if (c >= 0xf0 && c <= 0xf4) { need = 3; min = 0x10000; c &= 0x07; }
                else return false;
                if (end - i - 1 < need) return false;
                for (int k = 1; k <= need; k++)
                {
                    int cc = b[i + k];
                    if ((cc & 0xc0) != 0x80) return false;
                    c = (c << 6) | (cc & 0x3f);
                }
                if (c < min || c > 0x10ffff || (c >= 0xd800 && c <= 0xdfff)) return false;
                i += need + 1;
            }
            return true;
        }

        // ------------------------------------------------------------------ reading (after Validate)

        public MsgType PeekType()
        {
            if (_pos >= _end) return MsgType.Invalid;
            byte b = _buf[_pos];
            if (b <= 0x7f || b >= 0xe0) return MsgType.Int;
            if (b <= 0x8f) return MsgType.Map;
            if (b <= 0x9f) return MsgType.Array;
            if (b <= 0xbf) return MsgType.Str;
            switch (b)
            {
                case 0xc0: return MsgType.Nil;
                case 0xc2: case 0xc3: return MsgType.Bool;
                case 0xc4: case 0xc5: case 0xc6: return MsgType.Bin;
                case 0xca: case 0xcb: return MsgType.Float;
                case 0xcc: case 0xcd: case 0xce: case 0xcf:
                case 0xd0: case 0xd1: case 0xd2: case 0xd3: return MsgType.Int;
                case 0xd9: case 0xda: case 0xdb: return MsgType.Str;
                case 0xdc: case 0xdd: return MsgType.Array;
                case 0xde: case 0xdf: return MsgType.Map;
                case 0xc7: case 0xc8: case 0xc9: case 0xd4: case 0xd5: case 0xd6: case 0xd7: case 0xd8: return MsgType.Ext;
                default: return MsgType.Invalid;
            }
        }

        /// <summary>Name of the type at the cursor, as the Python reference names it (for messages).</summary>
        public string PeekTypeName()
        {
            switch (PeekType())
            {
                case MsgType.Nil: return "nil";
                case MsgType.Bool: return "bool";
                case MsgType.Int: return "int";
                case MsgType.Float: return "float";
                case MsgType.Str: return "str";
                case MsgType.Bin: return "bin";
                case MsgType.Array: return "array";
                case MsgType.Map: return "map";
                default: return "ext";
            }
        }

        ulong ReadBE(int width)
        {
            if (_end - _pos < width) throw Malformed("truncated value");
            ulong v = 0;
            for (int i = 0; i < width; i++) v = (v << 8) | _buf[_pos + i];
            _pos += width;
            return v;
        }

        byte ReadByte()
        {
            if (_pos >= _end) throw Malformed("truncated value");
            return _buf[_pos++];
        }

        public int ReadMapHeader()
        {
            byte b = ReadByte();
            if (b >= 0x80 && b <= 0x8f) return b & 0x0f;
            if (b == 0xde) return (int)ReadBE(2);
            if (b == 0xdf) { ulong n = ReadBE(4); if (n > int.MaxValue) throw Malformed("map too long"); return (int)n; }
            _pos--;
            throw new InvalidOperationException("not a map");
        }

        public int ReadArrayHeader()
        {
            byte b = ReadByte();
            if (b >= 0x90 && b <= 0x9f) return b & 0x0f;
            if (b == 0xdc) return (int)ReadBE(2);
            if (b == 0xdd) { ulong n = ReadBE(4); if (n > int.MaxValue) throw Malformed("array too long"); return (int)n; }
            _pos--;
            throw new InvalidOperationException("not an array");
        }

        public bool ReadBool()
        {
            byte b = ReadByte();
            if (b == 0xc2) return false;
            if (b == 0xc3) return true;
            _pos--;
            throw new InvalidOperationException("not a bool");
        }

        public bool TryReadNil()
        {
            if (_pos < _end && _buf[_pos] == 0xc0) { _pos++; return true; }
            return false;
        }

        /// <summary>
        /// Reads any msgpack integer. Values above long.MaxValue (uint64) set <paramref name="overflow"/>
        /// and return long.MaxValue.
        /// </summary>
        public long ReadInteger(out bool overflow)
        {
            overflow = false;
            byte b = ReadByte();
            if (b <= 0x7f) return b;
            if (b >= 0xe0) return (sbyte)b;
            switch (b)
            {
                case 0xcc: return (long)ReadBE(1);
                case 0xcd: return (long)ReadBE(2);
                case 0xce: return (long)ReadBE(4);
                case 0xcf:
                    {
                        ulong u = ReadBE(8);
                        if (u > long.MaxValue) { overflow = true; return long.MaxValue; }
                        return (long)u;
                    }
                case 0xd0: return (sbyte)ReadBE(1);
                case 0xd1: return (short)ReadBE(2);
                case 0xd2: return (int)ReadBE(4);
                case 0xd3: return (long)ReadBE(8);
            }
            _pos--;
            throw new InvalidOperationException("not an integer");
        }

        public long ReadInt64()
        {
            bool overflow;
            long v = ReadInteger(out overflow);
            if (overflow) throw new OverflowException("integer above Int64.MaxValue");
            return v;
        }

        public double ReadDouble()
        {
            byte b = ReadByte();
            if (b == 0xca) { uint u = (uint)ReadBE(4); return BitCast.UIntToFloat(u); }
            if (b == 0xcb) { ulong u = ReadBE(8); return BitConverter.Int64BitsToDouble((long)u); }
            _pos--;
            throw new InvalidOperationException("not a float");
        }

        /// <summary>Position and length of the UTF-8 bytes of the string at the cursor.</summary>
        public void ReadStringSegment(out int offset, out int length)
        {
            byte b = ReadByte();
            long n;
            if (b >= 0xa0 && b <= 0xbf) n = b & 0x1f;
            else if (b == 0xd9) n = (long)ReadBE(1);
            else if (b == 0xda) n = (long)ReadBE(2);
            else if (b == 0xdb) n = (long)ReadBE(4);
            else { _pos--; throw new InvalidOperationException("not a string"); }
            if (n > _end - _pos) throw Malformed("string beyond the end of the message");
            offset = _pos;
            length = (int)n;
            _pos += (int)n;
        }

        static readonly UTF8Encoding StrictUtf8 = new UTF8Encoding(false, true);

        public string ReadString()
        {
            int off, len;
            ReadStringSegment(out off, out len);
            try { return StrictUtf8.GetString(_buf, off, len); }
            catch (ArgumentException) { throw Malformed("invalid UTF-8 in a string"); }
        }

        /// <summary>Position and length of the payload of the bin at the cursor (no copy).</summary>
        public void ReadBinSegment(out int offset, out int length)
        {
            byte b = ReadByte();
            long n;
            if (b == 0xc4) n = (long)ReadBE(1);
            else if (b == 0xc5) n = (long)ReadBE(2);
            else if (b == 0xc6) n = (long)ReadBE(4);
            else { _pos--; throw new InvalidOperationException("not a bin"); }
            if (n > _end - _pos) throw Malformed("bin beyond the end of the message");
            offset = _pos;
            length = (int)n;
            _pos += (int)n;
        }

        /// <summary>Skips one complete value (containers included).</summary>
        public void Skip()
        {
            int pending = 1;
            while (pending > 0)
            {
                pending--;
                byte b = ReadByte();
                if (b <= 0x7f || b >= 0xe0) continue;
                if (b <= 0x8f) { pending += 2 * (b & 0x0f); continue; }
                if (b <= 0x9f) { pending += b & 0x0f; continue; }
                if (b <= 0xbf) { Advance(b & 0x1f); continue; }
                switch (b)
                {
                    case 0xc0: case 0xc2: case 0xc3: break;
                    case 0xc4: case 0xd9: Advance((long)ReadBE(1)); break;
                    case 0xc5: case 0xda: Advance((long)ReadBE(2)); break;
                    case 0xc6: case 0xdb: Advance((long)ReadBE(4)); break;
                    case 0xca: Advance(4); break;
                    case 0xcb: Advance(8); break;
                    case 0xcc: case 0xd0: Advance(1); break;
                    case 0xcd: case 0xd1: Advance(2); break;
                    case 0xce: case 0xd2: Advance(4); break;
                    case 0xcf: case 0xd3: Advance(8); break;
                    case 0xdc: pending += (int)ReadBE(2); break;
                    case 0xdd: pending += (int)ReadBE(4); break;
                    case 0xde: pending += 2 * (int)ReadBE(2); break;
                    case 0xdf: pending += 2 * (int)ReadBE(4); break;
                    default: throw Malformed("cannot skip byte 0x" + b.ToString("x2"));
                }
            }
        }

        void Advance(long n)
        {
            if (n > _end - _pos) throw Malformed("value beyond the end of the message");
            _pos += (int)n;
        }

        /// <summary>True if the UTF-8 bytes [offset, offset+length) of the buffer equal <paramref name="ascii"/>.</summary>
        public bool BytesEqual(int offset, int length, byte[] ascii)
        {
            if (length != ascii.Length) return false;
            for (int i = 0; i < length; i++) if (_buf[offset + i] != ascii[i]) return false;
            return true;
        }
    }

    /// <summary>
    /// msgpack writer into a reusable, growing byte buffer. Integers use the smallest form (as
    /// msgpack-python does), so encoded messages are byte-identical to the golden vectors.
    /// </summary>
    public sealed class MsgPackWriter
    {
        byte[] _buf;
        int _len;

        public MsgPackWriter(int capacity = 512) { _buf = new byte[Math.Max(16, capacity)]; }

        public byte[] Buffer { get { return _buf; } }
        public int Length { get { return _len; } }
        public void Clear() { _len = 0; }
        public ArraySegment<byte> Segment { get { return new ArraySegment<byte>(_buf, 0, _len); } }

        public byte[] ToArray()
        {
            byte[] r = new byte[_len];
            System.Buffer.BlockCopy(_buf, 0, r, 0, _len);
            return r;
        }

        void Ensure(int extra)
        {
            if (_len + extra <= _buf.Length) return;
            int n = _buf.Length;
            while (n < _len + extra) n *= 2;
            byte[] nb = new byte[n];
            System.Buffer.BlockCopy(_buf, 0, nb, 0, _len);
            _buf = nb;
        }

        void Byte(byte b) { Ensure(1); _buf[_len++] = b; }

        void BE(ulong v, int width)
        {
            Ensure(width);
            for (int i = width - 1; i >= 0; i--) { _buf[_len + i] = (byte)v; v >>= 8; }
            _len += width;
        }

        public void WriteMapHeader(int n)
        {
            if (n < 16) Byte((byte)(0x80 | n));
            else if (n <= 0xffff) { Byte(0xde); BE((ulong)n, 2); }
            else { Byte(0xdf); BE((ulong)n, 4); }
        }

        public void WriteArrayHeader(int n)
        {
            if (n < 16) Byte((byte)(0x90 | n));
            else if (n <= 0xffff) { Byte(0xdc); BE((ulong)n, 2); }
            else { Byte(0xdd); BE((ulong)n, 4); }
        }

        public void WriteNil() { Byte(0xc0); }
        public void WriteBool(bool v) { Byte(v ? (byte)0xc3 : (byte)0xc2); }

        public void WriteInt(long v)
        {
            if (v >= 0)
            {
                if (v <= 0x7f) Byte((byte)v);
                else if (v <= 0xff) { Byte(0xcc); BE((ulong)v, 1); }
                else if (v <= 0xffff) { Byte(0xcd); BE((ulong)v, 2); }
                else if (v <= 0xffffffffL) { Byte(0xce); BE((ulong)v, 4); }
                else { Byte(0xcf); BE((ulong)v, 8); }
            }
            else
            {
                if (v >= -32) Byte((byte)(sbyte)v);
                else if (v >= sbyte.MinValue) { Byte(0xd0); BE((ulong)v, 1); }
                else if (v >= short.MinValue) { Byte(0xd1); BE((ulong)v, 2); }
                else if (v >= int.MinValue) { Byte(0xd2); BE((ulong)v, 4); }
                else { Byte(0xd3); BE((ulong)v, 8); }
            }
        }

        public void WriteUInt64(ulong v)
        {
            if (v <= long.MaxValue) WriteInt((long)v);
            else { Byte(0xcf); BE(v, 8); }
        }

        public void WriteFloat32(float v) { Byte(0xca); BE(BitCast.FloatToUInt(v), 4); }
        public void WriteFloat64(double v) { Byte(0xcb); BE((ulong)BitConverter.DoubleToInt64Bits(v), 8); }

        public void WriteString(string s)
        {
            int n = Encoding.UTF8.GetByteCount(s);
            if (n < 32) Byte((byte)(0xa0 | n));
            else if (n <= 0xff) { Byte(0xd9); BE((ulong)n, 1); }
            else if (n <= 0xffff) { Byte(0xda); BE((ulong)n, 2); }
            else { Byte(0xdb); BE((ulong)n, 4); }
            Ensure(n);
            Encoding.UTF8.GetBytes(s, 0, s.Length, _buf, _len);
            _len += n;
        }

        public void WriteBinHeader(int n)
        {
            if (n <= 0xff) { Byte(0xc4); BE((ulong)n, 1); }
            else if (n <= 0xffff) { Byte(0xc5); BE((ulong)n, 2); }
            else { Byte(0xc6); BE((ulong)n, 4); }
        }

        public void WriteBin(byte[] data, int offset, int count)
        {
            WriteBinHeader(count);
            Ensure(count);
            System.Buffer.BlockCopy(data, offset, _buf, _len, count);
            _len += count;
        }

        /// <summary>bin of packed little-endian float32 values.</summary>
        public void WriteFloat32Bin(float[] values, int offset, int count)
        {
            WriteBinHeader(4 * count);
            Ensure(4 * count);
            if (BitConverter.IsLittleEndian)
                System.Buffer.BlockCopy(values, 4 * offset, _buf, _len, 4 * count);
            else
                for (int i = 0; i < count; i++) BitCast.WriteUInt32LE(_buf, _len + 4 * i, BitCast.FloatToUInt(values[offset + i]));
            _len += 4 * count;
        }

        /// <summary>Appends raw bytes (e.g. a pre-encoded value).</summary>
        public void WriteRaw(byte[] data, int offset, int count)
        {
            Ensure(count);
            System.Buffer.BlockCopy(data, offset, _buf, _len, count);
            _len += count;
        }
    }
}
