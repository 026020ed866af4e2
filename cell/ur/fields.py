"""The RTDE fields an e-Series controller (software 5.x) offers, by name, with their types (UR's RTDE
guide, "Field names and associated types"; the same as UR's client library's type list, whose
exhaustive output recipe of 406 fields is accepted whole).  A name not here is NOT_FOUND, as on a UR."""

from __future__ import annotations

from cell.ur.rtde import Type

D, V6, V3, I32, U32, U64, U8, B = (
    Type.DOUBLE, Type.VECTOR6D, Type.VECTOR3D, Type.INT32, Type.UINT32, Type.UINT64, Type.UINT8, Type.BOOL,
)  # fmt: skip

OUTPUTS: dict[str, Type] = {
    "timestamp": D,
    "target_q": V6, "target_qd": V6, "target_qdd": V6, "target_current": V6, "target_moment": V6,
    "actual_q": V6, "actual_qd": V6, "actual_qdd": V6, "actual_current": V6,
    "actual_current_as_torque": V6, "joint_control_output": V6,
    "actual_TCP_pose": V6, "actual_TCP_speed": V6, "actual_TCP_force": V6,
    "target_TCP_pose": V6, "target_TCP_speed": V6,
    "actual_digital_input_bits": U64, "joint_temperatures": V6, "actual_execution_time": D,
    "robot_mode": I32, "joint_mode": Type.VECTOR6INT32, "safety_mode": I32, "safety_status": I32,
    "actual_tool_accelerometer": V3, "speed_scaling": D, "target_speed_fraction": D,
    "actual_momentum": D, "actual_main_voltage": D, "actual_robot_voltage": D,
    "actual_robot_current": D, "actual_joint_voltage": V6, "actual_digital_output_bits": U64,
    "runtime_state": U32, "elbow_position": V3, "elbow_velocity": V3,
    "robot_status_bits": U32, "safety_status_bits": U32, "analog_io_types": U32,
    "standard_analog_input0": D, "standard_analog_input1": D,
    "standard_analog_output0": D, "standard_analog_output1": D, "io_current": D,
    "euromap67_input_bits": U32, "euromap67_output_bits": U32,
    "euromap67_24V_voltage": D, "euromap67_24V_current": D,
    "tool_mode": U32, "tool_analog_input_types": U32, "tool_analog_input0": D, "tool_analog_input1": D,
    "tool_output_voltage": I32, "tool_output_current": D, "tool_temperature": D,
    "tcp_force_scalar": D, "output_bit_registers0_to_31": U32, "output_bit_registers32_to_63": U32,
    "input_bit_registers0_to_31": U32, "input_bit_registers32_to_63": U32,
    "tool_output_mode": U8, "tool_digital_output0_mode": U8, "tool_digital_output1_mode": U8,
    "payload": D, "payload_cog": V3, "payload_inertia": V6, "script_control_line": U32,
    "ft_raw_wrench": V6, "joint_position_deviation_ratio": D, "collision_detection_ratio": D,
    "time_scale_source": I32,
    # (of later 5.x releases: in UR's client library's list and its exhaustive recipe)
    "actual_current_window": V6, "tcp_offset": V6,
    "actual_TCP_acceleration": V6, "target_TCP_acceleration": V6,
    "actual_configurable_digital_input_bits": U64, "actual_configurable_digital_output_bits": U64,
    "target_execution_time": D, "actual_robot_energy_consumed": D,
    "actual_robot_braking_energy_dissipated": D, "encoder0_raw": I32, "encoder1_raw": I32,
    "wrench_calc_from_currents": V6, "target_gravity": V3, "target_base_acceleration": V6,
    "control_step": U64, "target_base_wrench": V6,
    **{f"output_bit_register_{i}": B for i in range(64, 128)},
    **{f"output_int_register_{i}": I32 for i in range(48)},
    **{f"output_double_register_{i}": D for i in range(48)},
    **{f"input_bit_register_{i}": B for i in range(64, 128)},
    **{f"input_int_register_{i}": I32 for i in range(48)},
    **{f"input_double_register_{i}": D for i in range(48)},
}  # fmt: skip

INPUTS: dict[str, Type] = {
    "speed_slider_mask": U32, "speed_slider_fraction": D,
    "standard_digital_output_mask": U8, "standard_digital_output": U8,
    "configurable_digital_output_mask": U8, "configurable_digital_output": U8,
    "tool_digital_output_mask": U8, "tool_digital_output": U8,
    "standard_analog_output_mask": U8, "standard_analog_output_type": U8,
    "standard_analog_output_0": D, "standard_analog_output_1": D,
    "input_bit_registers0_to_31": U32, "input_bit_registers32_to_63": U32,
    "external_force_torque": V6, "ft_rtde_input_enable": B,
    **{f"input_bit_register_{i}": B for i in range(64, 128)},
    **{f"input_int_register_{i}": I32 for i in range(48)},
    **{f"input_double_register_{i}": D for i in range(48)},
}  # fmt: skip
