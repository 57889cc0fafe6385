// Unlit vertex-coloured points for PointCloudSink. Works with the built-in pipeline and URP (unlit pass
// without a LightMode tag); single-pass instanced stereo ready for Quest.
Shader "Ofera/Points"
{
    Properties
    {
        _PointSize ("Point size (pixels)", Float) = 2
        _AlphaCutoff ("Alpha cutoff", Range(0, 1)) = 0.05
    }
    SubShader
    {
        Tags { "RenderType" = "Opaque" "Queue" = "Geometry" }
        Cull Off
        Pass
        {
            CGPROGRAM
            #pragma vertex vert
            #pragma fragment frag
            #pragma multi_compile_instancing
            #include "UnityCG.cginc"

            float _PointSize;
            float _AlphaCutoff;

            struct appdata
            {
                float4 vertex : POSITION;
                fixed4 color : COLOR;
                UNITY_VERTEX_INPUT_INSTANCE_ID
            };

            struct v2f
            {
                float4 pos : SV_POSITION;
                fixed4 color : COLOR;
                float size : PSIZE;
                UNITY_VERTEX_OUTPUT_STEREO
            };

            v2f vert (appdata v)
            {
                v2f o;
                UNITY_SETUP_INSTANCE_ID(v);
                UNITY_INITIALIZE_VERTEX_OUTPUT_STEREO(o);
                o.pos = UnityObjectToClipPos(v.vertex);
                o.color = v.color;
                o.size = _PointSize;
                return o;
            }

            fixed4 frag (v2f i) : SV_Target
            {
                clip(i.color.a - _AlphaCutoff);
                return fixed4(i.color.rgb, 1);
            }
            ENDCG
        }
    }
}
