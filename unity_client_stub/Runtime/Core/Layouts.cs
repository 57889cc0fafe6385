// Blendshape layout names in wire order (protocol/ofera_protocol/layouts.py; Tests/TestMain.cs checks them against protocol/vectors/tables.json). UnityEngine-free.
using System;

namespace Ofera.Client
{
    public static class Layouts
    {
        public static readonly string[] Arkit52 =
        {
            "eyeBlinkLeft", "eyeLookDownLeft", "eyeLookInLeft", "eyeLookOutLeft", "eyeLookUpLeft", "eyeSquintLeft", "eyeWideLeft",
            "eyeBlinkRight", "eyeLookDownRight", "eyeLookInRight", "eyeLookOutRight", "eyeLookUpRight", "eyeSquintRight", "eyeWideRight",
            "jawForward", "jawLeft", "jawRight", "jawOpen",
            "mouthClose", "mouthFunnel", "mouthPucker", "mouthLeft", "mouthRight",
            "mouthSmileLeft", "mouthSmileRight", "mouthFrownLeft", "mouthFrownRight", "mouthDimpleLeft", "mouthDimpleRight",
            "mouthStretchLeft", "mouthStretchRight",
            "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper",
            "mouthPressLeft", "mouthPressRight", "mouthLowerDownLeft", "mouthLowerDownRight", "mouthUpperUpLeft", "mouthUpperUpRight",
            "browDownLeft", "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight",
            "cheekPuff", "cheekSquintLeft", "cheekSquintRight",
            "noseSneerLeft", "noseSneerRight",
            "tongueOut",
        };

        public static readonly string[] Ovr63 =
        {
            "BROW_LOWERER_L", "BROW_LOWERER_R", "CHEEK_PUFF_L", "CHEEK_PUFF_R", "CHEEK_RAISER_L", "CHEEK_RAISER_R",
            "CHEEK_SUCK_L", "CHEEK_SUCK_R", "CHIN_RAISER_B", "CHIN_RAISER_T", "DIMPLER_L", "DIMPLER_R",
            "EYES_CLOSED_L", "EYES_CLOSED_R", "EYES_LOOK_DOWN_L", "EYES_LOOK_DOWN_R", "EYES_LOOK_LEFT_L", "EYES_LOOK_LEFT_R",
            "EYES_LOOK_RIGHT_L", "EYES_LOOK_RIGHT_R", "EYES_LOOK_UP_L", "EYES_LOOK_UP_R",
            "INNER_BROW_RAISER_L", "INNER_BROW_RAISER_R", "JAW_DROP", "JAW_SIDEWAYS_LEFT", "JAW_SIDEWAYS_RIGHT", "JAW_THRUST",
            "LID_TIGHTENER_L", "LID_TIGHTENER_R",
            "LIP_CORNER_DEPRESSOR_L", "LIP_CORNER_DEPRESSOR_R", "LIP_CORNER_PULLER_L", "LIP_CORNER_PULLER_R",
            "LIP_FUNNELER_LB", "LIP_FUNNELER_LT", "LIP_FUNNELER_RB", "LIP_FUNNELER_RT",
            "LIP_PRESSOR_L", "LIP_PRESSOR_R", "LIP_PUCKER_L", "LIP_PUCKER_R", "LIP_STRETCHER_L", "LIP_STRETCHER_R",
            "LIP_SUCK_LB", "LIP_SUCK_LT", "LIP_SUCK_RB", "LIP_SUCK_RT", "LIP_TIGHTENER_L", "LIP_TIGHTENER_R",
            "LIPS_TOWARD", "LOWER_LIP_DEPRESSOR_L", "LOWER_LIP_DEPRESSOR_R", "MOUTH_LEFT", "MOUTH_RIGHT",
            "NOSE_WRINKLER_L", "NOSE_WRINKLER_R", "OUTER_BROW_RAISER_L", "OUTER_BROW_RAISER_R",
            "UPPER_LID_RAISER_L", "UPPER_LID_RAISER_R", "UPPER_LIP_RAISER_L", "UPPER_LIP_RAISER_R",
        };

        public static readonly string[] Ovr70 = Concat(Ovr63, new[]
        {
            "TONGUE_TIP_INTERDENTAL", "TONGUE_TIP_ALVEOLAR", "TONGUE_FRONT_DORSAL_PALATE", "TONGUE_MID_DORSAL_PALATE",
            "TONGUE_BACK_DORSAL_VELAR", "TONGUE_OUT", "TONGUE_RETREAT",
        });

        public static readonly string[] Arkit51 = Slice(Arkit52, 51);

        public static readonly string[] Mediapipe52 = MakeMediapipe();

        public static readonly string[] Livelink61 = MakeLivelink();

        /// <summary>Names of a layout in wire order, or null if unknown.</summary>
        public static string[] Names(string layout)
        {
            switch (layout)
            {
                case "arkit52": return Arkit52;
                case "arkit51": return Arkit51;
                case "mediapipe52": return Mediapipe52;
                case "ovr63": return Ovr63;
                case "ovr70": return Ovr70;
                case "livelink61": return Livelink61;
                default: return null;
            }
        }

        static string[] Concat(string[] a, string[] b)
        {
            string[] r = new string[a.Length + b.Length];
            Array.Copy(a, r, a.Length);
            Array.Copy(b, 0, r, a.Length, b.Length);
            return r;
        }

        static string[] Slice(string[] a, int n)
        {
            string[] r = new string[n];
            Array.Copy(a, r, n);
            return r;
        }

        static string[] MakeMediapipe()
        {
            string[] sorted = Slice(Arkit52, 51);
            Array.Sort(sorted, StringComparer.Ordinal);
            string[] r = new string[52];
            r[0] = "_neutral";
            Array.Copy(sorted, 0, r, 1, 51);
            return r;
        }

        static string[] MakeLivelink()
        {
            string[] r = new string[61];
            for (int i = 0; i < 52; i++) r[i] = char.ToUpperInvariant(Arkit52[i][0]) + Arkit52[i].Substring(1);
            string[] extra = { "HeadYaw", "HeadPitch", "HeadRoll", "LeftEyeYaw", "LeftEyePitch", "LeftEyeRoll", "RightEyeYaw", "RightEyePitch", "RightEyeRoll" };
            Array.Copy(extra, 0, r, 52, 9);
            return r;
        }
    }
}
