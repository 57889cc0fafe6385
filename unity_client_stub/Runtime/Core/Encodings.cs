// Frame encodings of protocol v1 (section 6): f32, f16 (IEEE binary16) and q13 (16-bit positions in
// a box, "smallest three" 10.10.10.2 rotations, 8-bit log scales). Decoders write into caller-owned
// float arrays. UnityEngine-free, C# 7.2, no unsafe code.
using System;
using System.Runtime.InteropServices;

namespace Ofera.Client
{
    /// <summary>float/uint reinterpretation without unsafe code (BitConverter.Int32BitsToSingle is not in every Unity profile).</summary>
    public static class BitCast
    {
        [StructLayout(LayoutKind.Explicit)]
        struct FloatUInt
        {
            [FieldOffset(0)] public float F;
            [FieldOffset(0)] public uint U;
        }

        public static float UIntToFloat(uint u) { FloatUInt x = default(FloatUInt); x.U = u; return x.F; }
        public static uint FloatToUInt(float f) { FloatUInt x = default(FloatUInt); x.F = f; return x.U; }

        public static uint ReadUInt32LE(byte[] b, int o)
        {
            return (uint)(b[o] | (b[o + 1] << 8) | (b[o + 2] << 16) | (b[o + 3] << 24));
        }

        public static ushort ReadUInt16LE(byte[] b, int o) { return (ushort)(b[o] | (b[o + 1] << 8)); }

        public static void WriteUInt32LE(byte[] b, int o, uint v)
        {
            b[o] = (byte)v; b[o + 1] = (byte)(v >> 8); b[o + 2] = (byte)(v >> 16); b[o + 3] = (byte)(v >> 24);
        }

        public static float ReadFloatLE(byte[] b, int o) { return UIntToFloat(ReadUInt32LE(b, o)); }

        public static bool IsFinite(float f) { return (FloatToUInt(f) & 0x7f800000u) != 0x7f800000u; }
    }

    /// <summary>IEEE 754 binary16 conversions (table-driven decode: 65536 floats, built once).</summary>
    public static class Half
    {
        static float[] _table;

        /// <summary>float32 value of every half bit pattern; NaN/infinity patterns map to NaN/infinity.</summary>
        public static float[] Table
        {
            get
            {
                float[] t = _table;
                if (t == null)
                {
                    t = new float[65536];
                    for (int i = 0; i < 65536; i++) t[i] = ToFloatSlow((ushort)i);
                    _table = t;
                }
                return t;
            }
        }

        public static float ToFloat(ushort h) { return Table[h]; }

        public static bool IsFinite(ushort h) { return (h & 0x7c00) != 0x7c00; }

        static float ToFloatSlow(ushort h)
        {
            uint sign = (uint)(h & 0x8000) << 16;
            int exp = (h >> 10) & 0x1f;
            uint mant = (uint)(h & 0x3ff);
            uint bits;
            if (exp == 0)
            {
                if (mant == 0) bits = sign;
                else
                {
                    // subnormal: value = mant * 2^-24, exact in float32
                    float v = mant * (1.0f / 16777216.0f);
                    return sign != 0 ? -v : v;
                }
            }
            else if (exp == 31) bits = sign | 0x7f800000u | (mant << 13);
            else bits = sign | ((uint)(exp - 15 + 127) << 23) | (mant << 13);
            return BitCast.UIntToFloat(bits);
        }

        /// <summary>float32 -> binary16, round to nearest even (for tests and tools; the client only decodes).</summary>
        public static ushort FromFloat(float f)
        {
            uint x = BitCast.FloatToUInt(f);
            uint sign = (x >> 16) & 0x8000;
            int exp = (int)((x >> 23) & 0xff);
            uint mant = x & 0x7fffff;
            if (exp == 255) return (ushort)(sign | 0x7c00 | (mant != 0 ? 0x200u : 0u));
            int e = exp - 127 + 15;
            if (e >= 31) return (ushort)(sign | 0x7c00);
            if (e <= 0)
            {
                if (e < -10) return (ushort)sign;
                mant |= 0x800000;
                int shift = 14 - e;
                uint halfMant = mant >> shift;
                uint rem = mant & ((1u << shift) - 1);
                uint halfway = 1u << (shift - 1);
                if (rem > halfway || (rem == halfway && (halfMant & 1) != 0)) halfMant++;
                return (ushort)(sign | halfMant);
            }
            uint hm = mant >> 13;
            uint r = mant & 0x1fff;
            uint res = sign | ((uint)e << 10) | hm;
            if (r > 0x1000 || (r == 0x1000 && (hm & 1) != 0)) res++;
            return (ushort)res;
        }
    }

    /// <summary>q13 session parameters (welcome.quant): position box and log-scale range, all float32.</summary>
    public sealed class Quant
    {
        public readonly float[] PosMin = new float[3];
        public readonly float[] PosMax = new float[3];
        public readonly float[] LogScale = new float[2];

        float[] _scaleTable;

        /// <summary>exp(lmin + q (lmax - lmin) / 255) for q = 0..255, computed in double, rounded to float32.</summary>
        public float[] ScaleTable
        {
            get
            {
                if (_scaleTable == null)
                {
                    float[] t = new float[256];
                    double lmin = LogScale[0], lmax = LogScale[1];
                    double step = (lmax - lmin) / 255.0;
                    for (int q = 0; q < 256; q++) t[q] = (float)Math.Exp(lmin + q * step);
                    _scaleTable = t;
                }
                return _scaleTable;
            }
        }

        /// <summary>Call after changing the arrays.</summary>
        public void Invalidate() { _scaleTable = null; }

        public Quant Clone()
        {
            Quant q = new Quant();
            Array.Copy(PosMin, q.PosMin, 3);
            Array.Copy(PosMax, q.PosMax, 3);
            Array.Copy(LogScale, q.LogScale, 2);
            return q;
        }
    }

    /// <summary>Decoders of frame payloads. Inputs are bin payloads (offset/length in a buffer).</summary>
    public static class FrameCodec
    {
        public const double Sqrt1_2 = 0.70710678118654757; // float(np.sqrt(0.5))
        public const int PosLevels = 65535;
        public const int RotLevels = 511;
        public const int ScaleLevels = 255;

        static readonly float RotStep = (float)(Sqrt1_2 / RotLevels);

        /// <summary>count little-endian float32 -> dst[dstOffset..]; false if any is NaN or infinite.</summary>
        public static bool DecodeF32(byte[] src, int srcOffset, int count, float[] dst, int dstOffset)
        {
            if (BitConverter.IsLittleEndian)
            {
                Buffer.BlockCopy(src, srcOffset, dst, 4 * dstOffset, 4 * count);
            }
            else
            {
                for (int i = 0; i < count; i++) dst[dstOffset + i] = BitCast.ReadFloatLE(src, srcOffset + 4 * i);
            }
            for (int i = 0; i < count; i++)
            {
                float v = dst[dstOffset + i];
                if (float.IsNaN(v) || float.IsInfinity(v)) return false;
            }
            return true;
        }

        /// <summary>count little-endian binary16 -> float32; false if any is NaN or infinite.</summary>
        public static bool DecodeF16(byte[] src, int srcOffset, int count, float[] dst, int dstOffset)
        {
            float[] table = Half.Table;
            bool finite = true;
            for (int i = 0; i < count; i++)
            {
                int o = srcOffset + 2 * i;
                int h = src[o] | (src[o + 1] << 8);
                if ((h & 0x7c00) == 0x7c00) finite = false;
                dst[dstOffset + i] = table[h];
            }
            return finite;
        }

        /// <summary>n x 3 uint16 -> positions: min + q (max - min) / 65535, in double, rounded to float32.</summary>
        public static void DecodeQ13Positions(byte[] src, int srcOffset, int n, Quant quant, float[] dst, int dstOffset)
        {
            double lo0 = quant.PosMin[0], lo1 = quant.PosMin[1], lo2 = quant.PosMin[2];
            double s0 = (quant.PosMax[0] - lo0) / PosLevels;
            double s1 = (quant.PosMax[1] - lo1) / PosLevels;
            double s2 = (quant.PosMax[2] - lo2) / PosLevels;
            for (int i = 0; i < n; i++)
            {
                int o = srcOffset + 6 * i;
                int d = dstOffset + 3 * i;
                dst[d] = (float)(lo0 + (src[o] | (src[o + 1] << 8)) * s0);
                dst[d + 1] = (float)(lo1 + (src[o + 2] | (src[o + 3] << 8)) * s1);
                dst[d + 2] = (float)(lo2 + (src[o + 4] | (src[o + 5] << 8)) * s2);
            }
        }

        /// <summary>n x 3 uint8 -> scales exp(lmin + q (lmax - lmin) / 255).</summary>
        public static void DecodeQ13Scales(byte[] src, int srcOffset, int n, Quant quant, float[] dst, int dstOffset)
        {
            float[] table = quant.ScaleTable;
            int m = 3 * n;
            for (int i = 0; i < m; i++) dst[dstOffset + i] = table[src[srcOffset + i]];
        }

        /// <summary>n uint32 "smallest three" 10.10.10.2 -> unit quaternions (x, y, z, w), float32 arithmetic.</summary>
        public static void DecodeQ13Rotations(byte[] src, int srcOffset, int n, float[] dst, int dstOffset)
        {
            for (int i = 0; i < n; i++)
            {
                uint v = BitCast.ReadUInt32LE(src, srcOffset + 4 * i);
                UnpackSmallestThree(v, dst, dstOffset + 4 * i);
            }
        }

        static int SignExtend10(uint f)
        {
            int s = (int)(f & 1023);
            s = (s ^ 512) - 512;
            return s < -RotLevels ? -RotLevels : s;
        }

        /// <summary>One 10.10.10.2 value -> (x, y, z, w) at dst[d..d+3].</summary>
        public static void UnpackSmallestThree(uint v, float[] dst, int d)
        {
            int idx = (int)(v >> 30);
            float a = (float)SignExtend10(v >> 20) * RotStep;
            float b = (float)SignExtend10(v >> 10) * RotStep;
            float c = (float)SignExtend10(v) * RotStep;
            float sum = (float)((float)(a * a) + (float)(b * b));
            sum = (float)(sum + (float)(c * c));
            float rest = (float)(1.0f - sum);
            float m = rest > 0f ? (float)Math.Sqrt(rest) : 0f;
            switch (idx)
            {
                case 0: dst[d] = m; dst[d + 1] = a; dst[d + 2] = b; dst[d + 3] = c; break;
                case 1: dst[d] = a; dst[d + 1] = m; dst[d + 2] = b; dst[d + 3] = c; break;
                case 2: dst[d] = a; dst[d + 1] = b; dst[d + 2] = m; dst[d + 3] = c; break;
                default: dst[d] = a; dst[d + 1] = b; dst[d + 2] = c; dst[d + 3] = m; break;
            }
        }

        /// <summary>(x, y, z, w) -> 10.10.10.2 as PROTOCOL.md 6.3 specifies (for tests and tools).</summary>
        public static uint PackSmallestThree(float x, float y, float z, float w)
        {
            float n2 = x * x + y * y + z * z + w * w;
            if (!(n2 > 0f) || float.IsInfinity(n2)) { x = 0f; y = 0f; z = 0f; w = 1f; n2 = 1f; }
            float ax = Math.Abs(x), ay = Math.Abs(y), az = Math.Abs(z), aw = Math.Abs(w);
            int i = 0; float best = ax;
            if (ay > best) { i = 1; best = ay; }
            if (az > best) { i = 2; best = az; }
            if (aw > best) { i = 3; }
            float dropped = i == 0 ? x : i == 1 ? y : i == 2 ? z : w;
            float f = (float)(Math.Sqrt(2.0) * RotLevels) / (float)Math.Sqrt(n2);
            if (dropped < 0) f = -f;
            float k0, k1, k2;
            switch (i)
            {
                case 0: k0 = y; k1 = z; k2 = w; break;
                case 1: k0 = x; k1 = z; k2 = w; break;
                case 2: k0 = x; k1 = y; k2 = w; break;
                default: k0 = x; k1 = y; k2 = z; break;
            }
            return ((uint)i << 30) | (Snorm10(k0 * f) << 20) | (Snorm10(k1 * f) << 10) | Snorm10(k2 * f);
        }

        static uint Snorm10(float v)
        {
            double r = Math.Round((double)v, MidpointRounding.ToEven);
            if (r > RotLevels) r = RotLevels;
            if (r < -RotLevels) r = -RotLevels;
            return (uint)((int)r & 0x3ff);
        }
    }
}
