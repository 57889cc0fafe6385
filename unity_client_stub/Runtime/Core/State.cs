// Coordinates (PROTOCOL.md section 8) and the client's per-Gaussian state (section 7).
// UnityEngine-free, C# 7.2.
using System;

namespace Ofera.Client
{
    /// <summary>
    /// FLAME (right-handed, y up, face +z) <-> Unity (left-handed): mirror x. Self-inverse.
    /// position (x,y,z) -> (-x,y,z); quaternion (x,y,z,w) -> (x,-y,-z,w); scale unchanged;
    /// SH coefficients odd in x (3DGS order 3, 4, 7, 10, 13, 15) change sign.
    /// </summary>
    public static class Coords
    {
        public static readonly int[] ShOddInX = { 3, 4, 7, 10, 13, 15 };

        public static void MirrorXPositions(float[] p, int offset, int n)
        {
            for (int i = 0; i < n; i++) p[offset + 3 * i] = -p[offset + 3 * i];
        }

        public static void MirrorXRotations(float[] q, int offset, int n)
        {
            for (int i = 0; i < n; i++)
            {
                int o = offset + 4 * i;
                q[o + 1] = -q[o + 1];
                q[o + 2] = -q[o + 2];
            }
        }

        /// <summary>sh: n x k x 3 coefficients.</summary>
        public static void MirrorXSh(float[] sh, int offset, int n, int k)
        {
            for (int i = 0; i < n; i++)
            {
                for (int j = 0; j < ShOddInX.Length; j++)
                {
                    int c = ShOddInX[j];
                    if (c >= k) break;
                    int o = offset + (i * k + c) * 3;
                    sh[o] = -sh[o]; sh[o + 1] = -sh[o + 1]; sh[o + 2] = -sh[o + 2];
                }
            }
        }

        public static void MirrorX(AvatarData a)
        {
            MirrorXPositions(a.Position, 0, a.Count);
            MirrorXRotations(a.Rotation, 0, a.Count);
            MirrorXSh(a.Sh, 0, a.Count, a.K);
        }

        public static void MirrorX(FrameData f)
        {
            MirrorXPositions(f.Position, 0, f.N);
            MirrorXRotations(f.Rotation, 0, f.N);
        }
    }

    /// <summary>
    /// Latest position/rotation/scale of every Gaussian in server order: starts at the neutral avatar;
    /// a dense frame replaces all, a sparse frame the listed Gaussians. Tracks the touched index range.
    /// </summary>
    public sealed class GaussianState
    {
        public readonly int Count;
        public readonly float[] Position;
        public readonly float[] Rotation;
        public readonly float[] Scale;

        /// <summary>Smallest and largest index changed since <see cref="ClearDirty"/> (Min > Max: none).</summary>
        public int DirtyMin, DirtyMax;

        public GaussianState(AvatarData avatar)
        {
            Count = avatar.Count;
            Position = (float[])avatar.Position.Clone();
            Rotation = (float[])avatar.Rotation.Clone();
            Scale = (float[])avatar.Scale.Clone();
            DirtyMin = 0;
            DirtyMax = Count - 1;
        }

        public void ClearDirty() { DirtyMin = int.MaxValue; DirtyMax = -1; }

        /// <summary>Applies a decoded frame of this session (false, and nothing changed, if it does not fit).</summary>
        public bool Apply(FrameData f)
        {
            if (!f.HasIndex)
            {
                if (f.N != Count) return false;
                Array.Copy(f.Position, Position, 3 * Count);
                Array.Copy(f.Rotation, Rotation, 4 * Count);
                Array.Copy(f.Scale, Scale, 3 * Count);
                if (Count > 0) { DirtyMin = 0; DirtyMax = Count - 1; }
                return true;
            }
            int n = f.N;
            if (n == 0) return true;
            if (f.Index[n - 1] >= (uint)Count) return false;
            uint[] idx = f.Index;
            float[] fp = f.Position, fr = f.Rotation, fs = f.Scale;
            for (int i = 0; i < n; i++)
            {
                int g = (int)idx[i];
                int p3 = 3 * g, i3 = 3 * i, p4 = 4 * g, i4 = 4 * i;
                Position[p3] = fp[i3]; Position[p3 + 1] = fp[i3 + 1]; Position[p3 + 2] = fp[i3 + 2];
                Rotation[p4] = fr[i4]; Rotation[p4 + 1] = fr[i4 + 1]; Rotation[p4 + 2] = fr[i4 + 2]; Rotation[p4 + 3] = fr[i4 + 3];
                Scale[p3] = fs[i3]; Scale[p3 + 1] = fs[i3 + 1]; Scale[p3 + 2] = fs[i3 + 2];
            }
            if ((int)idx[0] < DirtyMin) DirtyMin = (int)idx[0];
            if ((int)idx[n - 1] > DirtyMax) DirtyMax = (int)idx[n - 1];
            return true;
        }
    }
}
