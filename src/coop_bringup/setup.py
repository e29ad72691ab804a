"""colcon's ament_python set-up of coop_bringup (its package.xml says what it is)."""
from glob import glob

from setuptools import find_packages, setup

package_name = 'coop_bringup'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='Coop Field Robots maintainers',
    maintainer_email='maintainers@coop-field-robots.org',
    description='Launch files that bring up a team of cooperative rovers.',
    license='Apache-2.0',
    entry_points={'console_scripts': ['mission = coop_bringup.mission:main',
                                      'live_view = coop_bringup.live_view:main',
                                      'compose = coop_bringup.compose:main',
                                      'table_5_1 = coop_bringup.table_5_1:main',
                                      'appendix_a = coop_bringup.appendix_a:main']},
)
