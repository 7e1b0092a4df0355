-- A second database beside Prefect's: the Optuna studies.
CREATE DATABASE studies OWNER lidar;
