// Server-index -> GPU-index permutation for UnityGaussianSplatting assets (which Morton-reorder the
// splats on import), and UnityGaussianSplatting's GPU rotation packing. UnityEngine-free, C# 7.2,
// so it is tested under mono although the sink that uses it cannot be.
using System;
using System.Collections.Generic;

namespace Ofera.Client
{
    public static class SplatPermutation
    {
        /// <summary>
        /// Matches every server Gaussian (its neutral position) to the GPU splat at the same place.
        /// Tries the positions as they are and x-mirrored (an asset imported from a FLAME-space PLY while
        /// the session streams Unity coordinates, or the reverse) and keeps the better; then pairs each
        /// server Gaussian with the nearest unused GPU splat within <paramref name="tolerance"/> metres.
        /// Returns serverToGpu (length n, -1 where nothing matched).
        /// </summary>
        public static int[] Build(float[] serverPos, int n, float[] gpuPos, int m, float tolerance,
                                  out bool mirrorX, out int unmatched)
        {
            if (tolerance <= 0) tolerance = 1e-6f;
            float cell = Math.Max(tolerance, 1e-6f) * 2f;
            Dictionary<long, int> head = new Dictionary<long, int>(m);
            int[] next = new int[m];
            for (int j = 0; j < m; j++)
            {
                long key = CellKey(gpuPos[3 * j], gpuPos[3 * j + 1], gpuPos[3 * j + 2], cell);
                int h;
                next[j] = head.TryGetValue(key, out h) ? h : -1;
                head[key] = j;
            }
            bool[] used = new bool[m];
            // decide orientation on a sample
            int sample = Math.Min(n, 512);
            int hitsPlain = 0, hitsMirror = 0;
            for (int i = 0; i < sample; i++)
            {
                int k = i * Math.Max(1, n / Math.Max(1, sample));
                if (k >= n) break;
                if (Nearest(serverPos[3 * k], serverPos[3 * k + 1], serverPos[3 * k + 2], gpuPos, head, next, null, cell, tolerance) >= 0) hitsPlain++;
                if (Nearest(-serverPos[3 * k], serverPos[3 * k + 1], serverPos[3 * k + 2], gpuPos, head, next, null, cell, tolerance) >= 0) hitsMirror++;
            }
            mirrorX = hitsMirror > hitsPlain;
            float sx = mirrorX ? -1f : 1f;
            int[] map = new int[n];
            unmatched = 0;
            for (int i = 0; i < n; i++)
            {
                int j = Nearest(sx * serverPos[3 * i], serverPos[3 * i + 1], serverPos[3 * i + 2], gpuPos, head, next, used, cell, tolerance);
                map[i] = j;
                if (j < 0) unmatched++;
                else used[j] = true;
            }
            return map;
        }

        static long CellKey(float x, float y, float z, float cell)
        {
            long ix = (long)Math.Floor(x / cell) & 0x1fffff;
            long iy = (long)Math.Floor(y / cell) & 0x1fffff;
            long iz = (long)Math.Floor(z / cell) & 0x1fffff;
            return (ix << 42) | (iy << 21) | iz;
        }

        static int Nearest(float x, float y, float z, float[] gpuPos, Dictionary<long, int> head, int[] next, bool[] used,
                           float cell, float tolerance)
        {
            long cx = (long)Math.Floor(x / cell), cy = (long)Math.Floor(y / cell), cz = (long)Math.Floor(z / cell);
            int best = -1;
            double bestD = (double)tolerance * tolerance;
            for (long dx = -1; dx <= 1; dx++)
                for (long dy = -1; dy <= 1; dy++)
                    for (long dz = -1; dz <= 1; dz++)
                    {
                        long key = (((cx + dx) & 0x1fffff) << 42) | (((cy + dy) & 0x1fffff) << 21) | ((cz + dz) & 0x1fffff);
                        int j;
                        if (!head.TryGetValue(key, out j)) continue;
                        for (; j >= 0; j = next[j])
                        {
                            if (used != null && used[j]) continue;
                            double ddx = gpuPos[3 * j] - x, ddy = gpuPos[3 * j + 1] - y, ddz = gpuPos[3 * j + 2] - z;
                            double d = ddx * ddx + ddy * ddy + ddz * ddz;
                            if (d <= bestD) { bestD = d; best = j; }
                        }
                    }
            return best;
        }
    }

    /// <summary>
    /// UnityGaussianSplatting's rotation format on the GPU: its PackSmallest3Rotation (largest |component|
    /// dropped, others in order, sign from the dropped one, mapped to 0..1) then EncodeQuatToNorm10
    /// (x bits 0-9, y 10-19, z 20-29, index 30-31). Not the same bit layout as the protocol's q13.
    /// </summary>
    public static class UgsPacking
    {
        const float Sqrt2 = 1.41421356f;

        public static uint PackRotation(float x, float y, float z, float w)
        {
            // float32 operation order shared with the upload kernel (PackUgsRotation): tested bit-exact
            float n2 = (float)((float)((float)(x * x) + (float)(y * y)) + (float)(z * z));
            n2 = (float)(n2 + (float)(w * w));
            float len = (float)Math.Sqrt(n2);
            if (len > 0f && !float.IsInfinity(len))
            {
                float inv = (float)(1f / len);
                x = (float)(x * inv); y = (float)(y * inv); z = (float)(z * inv); w = (float)(w * inv);
            }
            else { x = 0f; y = 0f; z = 0f; w = 1f; }
            float ax = Math.Abs(x), ay = Math.Abs(y), az = Math.Abs(z), aw = Math.Abs(w);
            int index = 0; float maxV = ax;
            if (ay > maxV) { index = 1; maxV = ay; }
            if (az > maxV) { index = 2; maxV = az; }
            if (aw > maxV) { index = 3; }
            float a, b, c, d;
            switch (index)
            {
                case 0: a = y; b = z; c = w; d = x; break;
                case 1: a = x; b = z; c = w; d = y; break;
                case 2: a = x; b = y; c = w; d = z; break;
                default: a = x; b = y; c = z; d = w; break;
            }
            float s = d >= 0 ? 1f : -1f;
            a = (float)((float)((float)((float)(a * s) * Sqrt2) * 0.5f) + 0.5f);
            b = (float)((float)((float)((float)(b * s) * Sqrt2) * 0.5f) + 0.5f);
            c = (float)((float)((float)((float)(c * s) * Sqrt2) * 0.5f) + 0.5f);
            return Norm10(a) | (Norm10(b) << 10) | (Norm10(c) << 20) | ((uint)index << 30); // index = (uint)(index / 3f * 3.5f)
        }

        static uint Norm10(float v)
        {
            if (v < 0f) v = 0f;
            if (v > 1f) v = 1f;
            return (uint)(float)(v * 1023.5f);
        }

        /// <summary>Float32 bits the upload kernel writes into every hidden splat's position (a quiet NaN).</summary>
        public const uint HiddenPositionBits = 0x7fc00000u;

        /// <summary>
        /// CPU reference of the kernel CSOferaHide: every splat hidden (position NaN, which makes the
        /// renderer's vertex shader discard it; identity rotation; scale 0). pos: 3 words per splat, other: 4.
        /// </summary>
        public static void Hide(uint[] pos, uint[] other, int splats)
        {
            uint identity = PackRotation(0f, 0f, 0f, 1f);
            for (int i = 0; i < splats; i++)
            {
                pos[3 * i] = HiddenPositionBits; pos[3 * i + 1] = HiddenPositionBits; pos[3 * i + 2] = HiddenPositionBits;
                other[4 * i] = identity; other[4 * i + 1] = 0; other[4 * i + 2] = 0; other[4 * i + 3] = 0;
            }
        }

        /// <summary>
        /// CPU reference of the decode kernels: writes a decoded frame (server order, dense or sparse) into
        /// GPU-order words through serverToGpu (-1: skipped), mirroring x first when asked. Same bytes as
        /// CSOferaDecode* on the same frame (tests/test_unity_kernels.py).
        /// </summary>
        public static void WriteFrame(FrameData f, int[] serverToGpu, bool mirrorX, uint[] pos, uint[] other)
        {
            float[] p = f.Position, r = f.Rotation, s = f.Scale;
            for (int i = 0; i < f.N; i++)
            {
                int g = f.HasIndex ? (int)f.Index[i] : i;
                if (g < 0 || g >= serverToGpu.Length) continue;
                int d = serverToGpu[g];
                if (d < 0) continue;
                uint px = BitCast.FloatToUInt(p[3 * i]);
                float qx = r[4 * i], qy = r[4 * i + 1], qz = r[4 * i + 2], qw = r[4 * i + 3];
                if (mirrorX) { px ^= 0x80000000u; qy = -qy; qz = -qz; }
                pos[3 * d] = px;
                pos[3 * d + 1] = BitCast.FloatToUInt(p[3 * i + 1]);
                pos[3 * d + 2] = BitCast.FloatToUInt(p[3 * i + 2]);
                other[4 * d] = PackRotation(qx, qy, qz, qw);
                other[4 * d + 1] = BitCast.FloatToUInt(s[3 * i]);
                other[4 * d + 2] = BitCast.FloatToUInt(s[3 * i + 1]);
                other[4 * d + 3] = BitCast.FloatToUInt(s[3 * i + 2]);
            }
        }

        /// <summary>The shader's DecodeRotation (for tests): 10.10.10.2 -> (x, y, z, w).</summary>
        public static void UnpackRotation(uint enc, float[] dst, int d)
        {
            float px = (enc & 1023) / 1023f, py = ((enc >> 10) & 1023) / 1023f, pz = ((enc >> 20) & 1023) / 1023f;
            int idx = (int)(enc >> 30);
            float qx = px * Sqrt2 - 1f / Sqrt2, qy = py * Sqrt2 - 1f / Sqrt2, qz = pz * Sqrt2 - 1f / Sqrt2;
            float dot = qx * qx + qy * qy + qz * qz;
            if (dot > 1f) dot = 1f;
            float qw = (float)Math.Sqrt(1f - dot);
            switch (idx)
            {
                case 0: dst[d] = qw; dst[d + 1] = qx; dst[d + 2] = qy; dst[d + 3] = qz; break;
                case 1: dst[d] = qx; dst[d + 1] = qw; dst[d + 2] = qy; dst[d + 3] = qz; break;
                case 2: dst[d] = qx; dst[d + 1] = qy; dst[d + 2] = qw; dst[d + 3] = qz; break;
                default: dst[d] = qx; dst[d + 1] = qy; dst[d + 2] = qz; dst[d + 3] = qw; break;
            }
        }

        /// <summary>Floats per splat in UnityGaussianSplatting's Float32 SH data: sh1..sh15 (float3 each) and a float3 of padding.</summary>
        public const int ShFloat32Stride = 48;

        /// <summary>
        /// Mirrors x in UnityGaussianSplatting's Float32 SH data (GPU order): negates the coefficients whose
        /// basis is odd in x (3DGS order 3, 4, 7, 10, 13, 15; the DC term 0 lives in the colour texture).
        /// </summary>
        public static void MirrorXShFloat32(float[] sh, int splats)
        {
            for (int i = 0; i < splats; i++)
            {
                for (int j = 0; j < Coords.ShOddInX.Length; j++)
                {
                    int o = i * ShFloat32Stride + (Coords.ShOddInX[j] - 1) * 3;
                    sh[o] = -sh[o]; sh[o + 1] = -sh[o + 1]; sh[o + 2] = -sh[o + 2];
                }
            }
        }

        /// <summary>
        /// Writes Gaussians [from, to] of <paramref name="state"/> (server order) into GPU-order arrays:
        /// pos (3 floats per splat, Float32 position format) and other (4 uints per splat: packed rotation
        /// then Float32 scale x, y, z), through serverToGpu. mirrorX converts to the asset's handedness.
        /// Returns the GPU index range touched (min, max) via out parameters.
        /// </summary>
        public static void WriteGpu(GaussianState state, int from, int to, int[] serverToGpu, bool mirrorX,
                                    float[] pos, uint[] other, out int gpuMin, out int gpuMax)
        {
            gpuMin = int.MaxValue; gpuMax = -1;
            float sx = mirrorX ? -1f : 1f;
            float[] p = state.Position, r = state.Rotation, s = state.Scale;
            for (int i = from; i <= to; i++)
            {
                int g = serverToGpu[i];
                if (g < 0) continue;
                if (g < gpuMin) gpuMin = g;
                if (g > gpuMax) gpuMax = g;
                pos[3 * g] = sx * p[3 * i]; pos[3 * g + 1] = p[3 * i + 1]; pos[3 * g + 2] = p[3 * i + 2];
                float qx = r[4 * i], qy = r[4 * i + 1], qz = r[4 * i + 2], qw = r[4 * i + 3];
                if (mirrorX) { qy = -qy; qz = -qz; }
                other[4 * g] = PackRotation(qx, qy, qz, qw);
                other[4 * g + 1] = BitCast.FloatToUInt(s[3 * i]);
                other[4 * g + 2] = BitCast.FloatToUInt(s[3 * i + 1]);
                other[4 * g + 3] = BitCast.FloatToUInt(s[3 * i + 2]);
            }
        }
    }
}
